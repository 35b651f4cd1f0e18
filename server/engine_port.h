#pragma once
// What the daemon needs from the engine, as an interface: the shipped binary
// implements it over EngineSession (engine_adapter.h); tests may substitute a
// double, so the protocol, store and queue logic is tested without PETSc.
//
// The methods that run the engine are called on rank 0's engine thread only
// (MPI_THREAD_FUNNELED); label_table() and max_image_bytes() read what was
// fixed at construction and are also called on the socket thread.
#include <cstddef>
#include <filesystem>
#include <functional>
#include <map>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "core/label_table.h"
#include "core/tet_mesh.h"
#include "pipeline/given_labels_use.h"
#include "protocol/common.h"

namespace brainshift::server {

// stage, fraction of that stage in [0,1], seconds in it so far (final at 1).
// Same shape as brainshift::ProgressFn.
using StageProgressFn = std::function<void(const std::string& stage, double fraction, double seconds)>;

struct PreopImages {
  ImageF t1;
  LabelImage labels;  // same grid as t1, the values of the engine's label_table()
};

struct EngineScanOutput {
  // The parts that are not deferred (protocol/result_outputs.h), by their
  // stored names: field.nii, warped_image.nii, warped_labels.nii,
  // models/<structure>.vtp, timings.json. The client gzips plain NIfTI when
  // it writes register's .nii.gz names.
  std::map<std::string, std::string> files;
  protocol::ResultKindInfo result;  // nonrigid, or the affine-only fallback and why
  double intraop_seconds = 0.0;
};

class EnginePort {
 public:
  virtual ~EnginePort() = default;

  // The default preop atlas (built once, cached in cache_dir).
  virtual PreopImages load_default_atlas(const std::filesystem::path& cache_dir) = 0;
  // Meshes (or reuses stored_mesh), assembles and factorises on all ranks.
  // Throws InputError for bad input, other exceptions for failures; the
  // previous warm state stays in place on failure.
  virtual void load_preop(const PreopImages& preop, std::optional<TetMesh> stored_mesh,
                          double atlas_seconds, const StageProgressFn& progress) = 0;
  // The label table the engine was configured with (config/labels.toml or
  // the user's): the structures a preop label map may name, the values the
  // preop labels are mapped to, the models' short names.
  virtual const LabelTable& label_table() const = 0;
  virtual bool ready() const = 0;
  virtual const TetMesh& mesh() const = 0;  // requires ready()
  virtual nlohmann::json preop_timings() const = 0;
  // Runs the intraop stages and encodes the outputs. read_seconds (the
  // daemon's decoding of the pushed bytes) is added to the "read" timing, as
  // `brainshift register` adds its file reading. At least one of labels and
  // image: without labels the engine segments the image, and the outputs
  // then hold intraop_labels.nii and segmentation_confidence.nii, as they do
  // when labels with their image are refined by it (labels_use, unset: the
  // configuration's given_labels) and the refinement stands.
  virtual EngineScanOutput register_scan(const std::optional<LabelImage>& labels, const std::optional<ImageF>& image,
                                         std::optional<GivenLabelsUse> labels_use, double read_seconds,
                                         const StageProgressFn& progress) = 0;
  // The outputs of the scan register_scan last returned that are produced off
  // the latency path, after the result is stored and announced, in this
  // order: metrics.json (the label overlap figures judge the result; the
  // quality gates already ran), field.h5 (the same field as field.nii, in
  // ITK's encoding) and report.png (only with an intraop image). Each is
  // handed to `add` as soon as it is ready; nothing when already rendered.
  // Frees what it kept for them. scan_id titles the report.
  using DeferredOutputFn = std::function<void(const std::string& name, const std::string& bytes)>;
  virtual void render_deferred(const std::string& scan_id, const DeferredOutputFn& add) = 0;
  // field.h5 made from a stored field.nii (the same field in ITK's
  // encoding), for a result whose field.h5 was lost to a crash; nullopt when
  // the engine cannot make it.
  virtual std::optional<std::string> itk_field_from_nifti(const std::string& /*field_nii*/) {
    return std::nullopt;
  }
  virtual int ranks() const = 0;
  // Bound on decompressed image bytes received from clients.
  virtual std::size_t max_image_bytes() const = 0;
  virtual void stop_workers() = 0;
};

}  // namespace brainshift::server
