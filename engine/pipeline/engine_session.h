#pragma once
// The engine as a long-lived session: preop state kept warm, one call per scan.
//
// MPI shape (as PETSc's PCMPIServerBegin): rank 0 owns the session and drives
// it; ranks > 0 sit in run_worker_loop() and take part in every collective
// step (mesh broadcast, assembly, factorisation, each solve) when rank 0
// broadcasts a command. Under one process the same code runs with no workers.
// Success or failure of a collective step is agreed on all ranks before
// rank 0 returns, so no rank is left waiting.
#include <mpi.h>

#include <functional>
#include <map>
#include <memory>
#include <filesystem>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "core/tet_mesh.h"
#include "pipeline/pipeline_parameters.h"
#include "protocol/result_kind.h"

namespace brainshift {

// stage: e.g. "mesh", "assemble", "factorise", "affine", "surface", "solve";
// fraction in [0,1]; seconds spent in the stage so far (final when fraction 1).
using ProgressFn = std::function<void(const std::string& stage, double fraction, double seconds)>;

struct PreopInput {
  ImageF t1;
  LabelImage labels;  // same grid as t1
};

// What the stages work on: the intraop labels always present (given, or
// derived by the prepare step from the image).
struct IntraopInput {
  LabelImage labels;          // 1 brain, 2 lateral ventricles (table values)
  std::optional<ImageF> t1;   // same grid as labels when given
  // The caller's reading or decoding of these images: counted in the
  // scan's "read" and "total" timings (run_intraop writes them all).
  double read_seconds = 0.0;
  // Fluid the automatic segmentation found where the brain was (the gap a
  // sinking leaves): the volume gate counts it with the brain. 0 for labels
  // a caller gives.
  double open_fluid_ml = 0.0;
};

// A scan as it arrives: an image, labels, or both (at least one). Without
// labels the engine segments the image first (pipeline/prepare_stage.h).
struct ScanInput {
  std::optional<LabelImage> labels;
  std::optional<ImageF> image;  // same grid as labels when both are given
  double read_seconds = 0.0;    // as IntraopInput::read_seconds
  // Labels with an image: how they are used; unset = the configured
  // AutoSegmentationParameters::given_labels.
  std::optional<GivenLabelsUse> labels_use;
};

// nonrigid, or affine_only_fallback when a non-rigid stage failed a quality
// gate (the field is then the affine alone): the protocol's one enum.
using ResultKind = protocol::ResultKind;

struct ScanResult {
  ResultKind kind = ResultKind::nonrigid;
  std::string fallback_reason;          // why, when kind is affine_only_fallback
  VectorImage3 pullback_field_mm;       // intraop grid, x + u(x) = preop point
  Eigen::Matrix4d intraop_from_preop = Eigen::Matrix4d::Identity();
  ImageF warped_t1;                     // preop T1 on the intraop grid
  ImageF warped_t1_affine_only;         // the same through the affine alone (for the report)
  LabelImage warped_labels;             // preop labels on the intraop grid
  std::map<std::string, TriSurface> models;  // preop structures, intraop frame
  std::vector<Eigen::Vector3d> nonrigid_node_mm;  // per mesh node, beyond the affine (zero on fallback)
  // 95 % band radius (mm) on the intraop grid; empty until add_uncertainty().
  ImageF uncertainty_mm;
  nlohmann::json metrics;
  nlohmann::json timings;  // {"preop": {...}, "intraop": {...}, "mesh": {...}}
  // Set when the engine derived the intraop labels from the image (no labels
  // given): the segmentation the stages used and the posterior of its choice.
  std::optional<LabelImage> intraop_labels;
  std::optional<ImageF> segmentation_confidence;
  // Set when given labels were registered with fluid spaces taken back
  // (pipeline/preop_fluid_spaces_stage.h) and no segmentation replaced
  // them: the labels the stages used, which the deferred parts (quality
  // figures, uncertainty) judge. Not a result part (PROTOCOL.md 5.3).
  std::optional<LabelImage> given_labels_used;
  // The labels the stages registered: the engine's segmentation, else the
  // given labels as used, else those pushed (an image alone has none: its
  // result always holds the segmentation).
  const LabelImage& labels_used(const std::optional<LabelImage>& pushed) const {
    if (intraop_labels) return *intraop_labels;
    if (given_labels_used) return *given_labels_used;
    return pushed.value();
  }
};

// A non-rigid result to be read with care says why in metrics "caution"
// (PROTOCOL.md 5.4): given labels refused or changed grossly by their
// image, an image that looks contrast-enhanced. Each reason is appended.
inline void add_caution(nlohmann::json& metrics, const std::string& why) {
  const std::string before = metrics.is_object() ? metrics.value("caution", "") : "";
  metrics["caution"] = before.empty() ? why : before + "; " + why;
}
// The result's caution; empty when it need not be read with care.
inline std::string result_caution(const nlohmann::json& metrics) {
  return metrics.is_object() && metrics.contains("caution") && metrics["caution"].is_string()
             ? metrics["caution"].get<std::string>()
             : std::string();
}

struct WarmState;  // mesh, surfaces, bindings, FEM model: see engine_session.cpp

class EngineSession {
 public:
  // Rank 0 only. comm must be the communicator the workers loop on.
  EngineSession(MPI_Comm comm, PipelineParameters params);
  ~EngineSession();
  EngineSession(const EngineSession&) = delete;
  EngineSession& operator=(const EngineSession&) = delete;

  // Meshes the preop labels (or uses stored_mesh, e.g. after a restart, so the
  // mesh never changes), assembles and factorises on all ranks, builds surface
  // models. Replaces any previous warm state only on success.
  void load_preop(PreopInput input, const ProgressFn& progress,
                  std::optional<TetMesh> stored_mesh = std::nullopt);
  bool ready() const;
  const TetMesh& mesh() const;            // requires ready()
  const PreopInput& preop() const;        // requires ready()
  nlohmann::json preop_timings() const;   // {"atlas","mesh","assemble","factorise","total"}
  void set_atlas_seconds(double seconds); // time spent reading/building the preop inputs

  // Runs the intraop stages (affine, surfaces, solve, field, warp, models,
  // metrics). Throws InputError for bad input; quality-gate failures return an
  // affine_only_fallback result, never a silent bad field.
  // With defer_quality_metrics, result.metrics lacks the label overlap
  // figures ("labels", "labels_affine_only") and warped_t1_affine_only is
  // empty until add_quality_metrics(): the daemon announces the field first.
  ScanResult register_scan(const IntraopInput& input, const ProgressFn& progress,
                           bool defer_quality_metrics = false);
  // The same for a scan that may lack labels: the prepare step segments the
  // image (a "segment" stage in the timings) and iterates the segmentation
  // with the registration; result.intraop_labels holds what was used, and
  // add_quality_metrics() takes prepared_input(result).
  ScanResult register_scan(const ScanInput& scan, const ProgressFn& progress,
                           bool defer_quality_metrics = false);
  void add_quality_metrics(const IntraopInput& input, ScanResult& result, const ProgressFn& progress) const;
  // The uncertainty map (quality/uncertainty_map.h) of a result of this
  // session's warm state: Monte Carlo solves on the warm factorisation, so it
  // is collective like register_scan; called after the answer is served.
  void add_uncertainty(const IntraopInput& input, ScanResult& result, const ProgressFn& progress);

  // Tells the workers to leave run_worker_loop (also done by the destructor).
  void stop_workers();

  const PipelineParameters& parameters() const { return params_; }
  int ranks() const;

 private:
  ScanResult register_scan_as_given(const ScanInput& scan, const ProgressFn& progress, bool defer_quality_metrics);
  void report_lift(ScanResult& result, double intraop_by) const;

  MPI_Comm comm_;
  PipelineParameters params_;
  std::unique_ptr<WarmState> warm_;
  // Intraop and preop images with negative values (a stored intercept, a
  // z-scored export) are lifted to a magnitude image's range before use, by
  // every entry point alike (image/intensity_offset.h); the preop T1's lift:
  double preop_lifted_by_ = 0;
  double atlas_seconds_ = 0;
  bool workers_stopped_ = false;
};

// Ranks > 0: serve collective commands from rank 0 until it stops them.
void run_worker_loop(MPI_Comm comm);

}  // namespace brainshift
