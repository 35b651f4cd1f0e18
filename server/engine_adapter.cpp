#include "server/engine_adapter.h"

#include <chrono>
#include <future>

#include "atlas/default_atlas.h"
#include "core/errors.h"
#include "field/itk_transform_io.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "pipeline/scan_report.h"
#include "server/hdf5_file.h"

namespace brainshift::server {
namespace fs = std::filesystem;

namespace {

// The daemon's encoding of register's outputs: the same content, but chosen
// for latency. Images are plain NIfTI (gzip of the 47 MB field alone took
// ~1.5 s; the client gzips when it writes field.nii.gz). metrics.json,
// field.h5 and report.png are left out here: made after the scan is announced
// (see render_deferred). The label overlap metrics take ~0.3 s and judge the
// result rather than make it (the quality gates ran before); field.h5 repeats
// field.nii and its 47 MB cost ~0.35 s of encoding and fsync. Encoded in
// memory: no scratch folder written and read back.
std::map<std::string, std::string> encode_outputs(const ScanResult& r) {
  std::map<std::string, std::string> files;
  // The field (47 MB, half of the bytes) on the second core, the rest here.
  auto field = std::async(std::launch::async,
                          [&r] { return displacement_field_to_bytes(r.pullback_field_mm, /*gzip=*/false); });
  files["warped_image.nii"] = scalar_image_to_bytes(r.warped_t1, VoxelType::float32, /*gzip=*/false);
  files["warped_labels.nii"] = label_image_to_bytes(r.warped_labels, /*gzip=*/false);
  for (const auto& [name, surface] : r.models) files["models/" + name + ".vtp"] = vtp_bytes(surface);
  files["timings.json"] = r.timings.dump(2) + "\n";
  files["field.nii"] = field.get();
  return files;
}

}  // namespace

EngineAdapter::EngineAdapter(MPI_Comm comm, PipelineParameters params) : session_(comm, std::move(params)) {}

PreopImages EngineAdapter::load_default_atlas(const fs::path& cache_dir) {
  DefaultAtlas atlas = load_or_build_default_atlas(cache_dir);
  return PreopImages{std::move(atlas.t1), std::move(atlas.labels)};
}

void EngineAdapter::load_preop(const PreopImages& preop, std::optional<TetMesh> stored_mesh,
                               double atlas_seconds, const StageProgressFn& progress) {
  session_.load_preop(PreopInput{preop.t1, preop.labels}, progress, std::move(stored_mesh));
  session_.set_atlas_seconds(atlas_seconds);
}

EngineScanOutput EngineAdapter::register_scan(const LabelImage& labels, const std::optional<ImageF>& image,
                                              double read_seconds, const fs::path& /*scratch_dir*/,
                                              const StageProgressFn& progress) {
  deferred_.reset();
  ScanResult result = session_.register_scan(IntraopInput{labels, image}, progress, /*defer_quality_metrics=*/true);
  auto& intraop = result.timings["intraop"];
  intraop["read"] = intraop.value("read", 0.0) + read_seconds;
  intraop["total"] = intraop.value("total", 0.0) + read_seconds;
  const auto t_outputs = std::chrono::steady_clock::now();
  progress("outputs", 0.0, 0.0);
  EngineScanOutput output;
  output.files = encode_outputs(result);
  progress("outputs", 1.0, std::chrono::duration<double>(std::chrono::steady_clock::now() - t_outputs).count());
  output.kind = result.kind == ResultKind::nonrigid ? "nonrigid" : "affine_only_fallback";
  output.fallback_reason = result.fallback_reason;
  output.intraop_seconds = intraop.value("total", 0.0);
  deferred_ = std::make_unique<Deferred>(Deferred{IntraopInput{labels, image}, std::move(result)});
  return output;
}

namespace {

std::string itk_field_bytes(const VectorImage3& field) {
  // float32 like field.nii, so nothing is lost against it. HDF5 is not
  // thread-safe in this build: the store's lock keeps the socket thread out.
  ItkTransformWriteOptions itk;
  itk.single_precision = true;
  std::lock_guard lock(h5::hdf5_mutex());
  return itk_displacement_transform_bytes(field, itk);
}

}  // namespace

std::optional<std::string> EngineAdapter::itk_field_from_nifti(const std::string& field_nii) {
  return itk_field_bytes(vector_image_from_bytes(field_nii, "field.nii", field_nii.size() + (1u << 20)));
}

void EngineAdapter::render_deferred(const std::string& scan_id, const DeferredOutputFn& add) {
  if (!deferred_) return;
  const std::unique_ptr<Deferred> d = std::move(deferred_);
  ScanResult& r = d->result;
  session_.add_quality_metrics(d->input, r, nullptr);
  add("metrics.json", r.metrics.dump(2) + "\n");
  add("field.h5", itk_field_bytes(r.pullback_field_mm));
  // The picture needs an intraop image to draw on (as in register).
  if (!d->input.t1) return;
  add("report.png", scan_report_png(r, *d->input.t1, session_.parameters().label_table, scan_id));
}

}  // namespace brainshift::server
