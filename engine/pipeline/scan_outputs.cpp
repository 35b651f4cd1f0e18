// The one encoder of a registration's outputs, and register's folder of them.
#include "pipeline/scan_outputs.h"

#include <fstream>
#include <future>
#include <random>

#include "core/errors.h"
#include "field/itk_transform_io.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "pipeline/scan_report.h"
#include "protocol/result_outputs.h"

namespace brainshift {
namespace fs = std::filesystem;
using protocol::ResultPart;

namespace {

std::string name_of(ResultPart part, ImageEncoding images) {
  const protocol::ResultOutput& o = protocol::result_output(part);
  return std::string(images == ImageEncoding::gzip ? o.file : o.stored);
}

std::string json_text(const nlohmann::json& value) { return value.dump(2) + "\n"; }

fs::path sibling_temp_dir(const fs::path& out_dir) {
  std::random_device rd;
  const fs::path parent = out_dir.has_parent_path() ? out_dir.parent_path() : fs::path(".");
  return parent / ("." + out_dir.filename().string() + ".partial-" + std::to_string(rd()));
}

void write_file(const fs::path& path, const std::string& bytes) {
  fs::create_directories(path.parent_path());
  std::ofstream out(path, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (!out) throw InputError(path.string() + ": cannot write");
}

}  // namespace

EncodedOutputs encode_scan_outputs(const ScanResult& r, ImageEncoding images) {
  const bool gzip = images == ImageEncoding::gzip;
  // The field (47 MB at 1 mm, half of the bytes) on the second core, the rest here.
  auto field = std::async(std::launch::async,
                          [&r, gzip] { return displacement_field_to_bytes(r.pullback_field_mm, gzip); });
  EncodedOutputs files;
  files[name_of(ResultPart::kWarpedImage, images)] = scalar_image_to_bytes(r.warped_t1, VoxelType::float32, gzip);
  files[name_of(ResultPart::kWarpedLabels, images)] = label_image_to_bytes(r.warped_labels, gzip);
  for (const auto& [name, surface] : r.models) files[protocol::model_file_name(name)] = vtp_bytes(surface);
  files[name_of(ResultPart::kTimings, images)] = json_text(r.timings);
  if (r.intraop_labels)
    files[name_of(ResultPart::kIntraopLabels, images)] = label_image_to_bytes(*r.intraop_labels, gzip);
  if (r.segmentation_confidence)
    files[name_of(ResultPart::kSegmentationConfidence, images)] =
        scalar_image_to_bytes(*r.segmentation_confidence, VoxelType::float32, gzip);
  files[name_of(ResultPart::kDisplacement, images)] = field.get();
  return files;
}

void encode_deferred_outputs(const ScanResult& r, const ImageF* intraop_t1, const DeferredOutputOptions& options,
                             const OutputFn& add) {
  add(std::string(protocol::result_output(ResultPart::kMetrics).file), json_text(r.metrics));
  if (!r.uncertainty_mm.voxels.empty())
    add(name_of(ResultPart::kUncertainty, options.images),
        scalar_image_to_bytes(r.uncertainty_mm, VoxelType::float32, options.images == ImageEncoding::gzip));
  ItkTransformWriteOptions itk;
  itk.single_precision = options.itk_single_precision;
  {
    std::unique_lock<std::mutex> lock;
    if (options.hdf5_mutex) lock = std::unique_lock(*options.hdf5_mutex);
    add(std::string(protocol::result_output(ResultPart::kDisplacementItk).file),
        itk_displacement_transform_bytes(r.pullback_field_mm, itk));
  }
  // The picture needs an intraop image to draw on; without one there is none.
  if (!intraop_t1 || !options.report) return;
  if (!options.label_table) throw std::invalid_argument("encode_deferred_outputs: the report needs a label table");
  add(std::string(protocol::result_output(ResultPart::kReport).file),
      scan_report_png(r, *intraop_t1, *options.label_table, options.scan_id));
}

void write_scan_outputs(const ScanResult& result, const ImageF* intraop_t1, const fs::path& out_dir,
                        const DeferredOutputOptions& options) {
  const fs::path temp = sibling_temp_dir(out_dir);
  try {
    if (out_dir.has_parent_path()) fs::create_directories(out_dir.parent_path());
    fs::create_directories(temp / "models");
    for (const auto& [name, bytes] : encode_scan_outputs(result, ImageEncoding::gzip)) write_file(temp / name, bytes);
    DeferredOutputOptions gzipped = options;
    gzipped.images = ImageEncoding::gzip;
    encode_deferred_outputs(result, intraop_t1, gzipped,
                            [&](const std::string& name, const std::string& bytes) { write_file(temp / name, bytes); });
    // A previous result in out_dir is replaced only once the new one is complete.
    if (fs::exists(out_dir)) fs::remove_all(out_dir);
    fs::rename(temp, out_dir);
  } catch (const fs::filesystem_error& e) {
    std::error_code ignored;
    fs::remove_all(temp, ignored);
    throw InputError(out_dir.string() + ": cannot write the outputs (" + e.what() + ")");
  } catch (...) {
    std::error_code ignored;
    fs::remove_all(temp, ignored);
    throw;
  }
}

}  // namespace brainshift
