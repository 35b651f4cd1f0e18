#include "server/engine_adapter.h"

#include <chrono>

#include "atlas/default_atlas.h"
#include "core/errors.h"
#include "field/itk_transform_io.h"
#include "image/nifti_io.h"
#include "pipeline/scan_outputs.h"
#include "pipeline/scan_report.h"
#include "protocol/result_outputs.h"
#include "protocol/stage_names.h"
#include "server/hdf5_file.h"

namespace brainshift::server {
namespace fs = std::filesystem;

EngineAdapter::EngineAdapter(MPI_Comm comm, PipelineParameters params) : session_(comm, std::move(params)) {}

PreopImages EngineAdapter::load_default_atlas(const fs::path& cache_dir) {
  DefaultAtlas atlas = load_or_build_default_atlas(cache_dir);
  return PreopImages{std::move(atlas.t1), atlas_labels_for(atlas.labels, session_.parameters().label_table)};
}

void EngineAdapter::load_preop(const PreopImages& preop, std::optional<TetMesh> stored_mesh,
                               double atlas_seconds, const StageProgressFn& progress) {
  session_.load_preop(PreopInput{preop.t1, preop.labels}, progress, std::move(stored_mesh));
  session_.set_atlas_seconds(atlas_seconds);
}

// The latency path holds only what the surgeon needs: images as plain NIfTI
// (gzip of the 47 MB field alone took ~1.5 s; the client gzips as it writes
// field.nii.gz). metrics.json, field.h5 and report.png follow the
// announcement (render_deferred): the label overlap metrics take ~0.3 s and
// judge the result rather than make it (the quality gates ran before);
// field.h5 repeats field.nii and cost ~0.35 s of encoding and fsync.
EngineScanOutput EngineAdapter::register_scan(const std::optional<LabelImage>& labels,
                                              const std::optional<ImageF>& image,
                                              std::optional<GivenLabelsUse> labels_use, double read_seconds,
                                              const StageProgressFn& progress) {
  deferred_.reset();
  ScanResult result =
      session_.register_scan(brainshift::ScanInput{labels, image, read_seconds, labels_use}, progress,
                             /*defer_quality_metrics=*/true);
  const auto t_outputs = std::chrono::steady_clock::now();
  const std::string outputs_stage(protocol::stages::kOutputs);
  progress(outputs_stage, 0.0, 0.0);
  EngineScanOutput output;
  output.files = encode_scan_outputs(result, ImageEncoding::plain);
  progress(outputs_stage, 1.0, std::chrono::duration<double>(std::chrono::steady_clock::now() - t_outputs).count());
  output.result = {result.kind, result.fallback_reason, result_caution(result.metrics)};
  output.intraop_seconds = result.timings["intraop"].value(std::string(protocol::stages::kTotal), 0.0);
  // The deferred parts judge the labels the stages used: the engine's
  // segmentation of the image when it made one (an image alone, or labels
  // refined by their image), else those pushed with the fluid spaces they
  // took back (ScanResult::labels_used).
  const LabelImage& used = result.labels_used(labels);
  deferred_ = std::make_unique<Deferred>(Deferred{IntraopInput{used, image}, std::move(result)});
  return output;
}

std::optional<std::string> EngineAdapter::itk_field_from_nifti(const std::string& field_nii) {
  // float32 like field.nii, so nothing is lost against it. HDF5 is not
  // thread-safe in this build: the store's lock keeps the socket thread out.
  ItkTransformWriteOptions itk;
  itk.single_precision = true;
  const VectorImage3 field = vector_image_from_bytes(field_nii, "field.nii", field_nii.size() + (1u << 20));
  std::lock_guard lock(h5::hdf5_mutex());
  return itk_displacement_transform_bytes(field, itk);
}

void EngineAdapter::render_deferred(const std::string& scan_id, const DeferredOutputFn& add) {
  if (!deferred_) return;
  const std::unique_ptr<Deferred> d = std::move(deferred_);
  ScanResult& r = d->result;
  session_.add_quality_metrics(d->input, r, nullptr);
  DeferredOutputOptions options;
  options.itk_single_precision = true;  // as field.nii holds it
  options.label_table = &session_.parameters().label_table;
  options.scan_id = scan_id;
  options.hdf5_mutex = &h5::hdf5_mutex();
  options.report = false;  // drawn last, with the uncertainty map's row
  encode_deferred_outputs(r, d->input.t1 ? &*d->input.t1 : nullptr, options,
                          [&](const std::string& name, const std::string& bytes) { add(name, bytes); });
  // The uncertainty map next (seconds of solves): metrics.json and field.h5
  // do not wait for it, so the daemon's metrics.json lacks its summary
  // (register's has it). report.png waits for it, to show the band.
  session_.add_uncertainty(d->input, r, nullptr);
  add(std::string(protocol::result_output(protocol::ResultPart::kUncertainty).stored),
      scalar_image_to_bytes(r.uncertainty_mm, VoxelType::float32, false));
  if (d->input.t1)
    add(std::string(protocol::result_output(protocol::ResultPart::kReport).file),
        scan_report_png(r, *d->input.t1, *options.label_table, scan_id));
}

}  // namespace brainshift::server
