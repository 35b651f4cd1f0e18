// Writing one registration's outputs as a folder, all or nothing.
#include <fstream>
#include <random>

#include "core/errors.h"
#include "field/itk_transform_io.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "pipeline/engine_session.h"
#include "pipeline/scan_report.h"

namespace brainshift {
namespace fs = std::filesystem;
namespace {

void write_json(const fs::path& path, const nlohmann::json& value) {
  std::ofstream out(path);
  out << value.dump(2) << '\n';
  if (!out) throw InputError(path.string() + ": cannot write");
}

fs::path sibling_temp_dir(const fs::path& out_dir) {
  std::random_device rd;
  const fs::path parent = out_dir.has_parent_path() ? out_dir.parent_path() : fs::path(".");
  return parent / ("." + out_dir.filename().string() + ".partial-" + std::to_string(rd()));
}

void write_all(const ScanResult& r, const ImageF* intraop_t1, const fs::path& dir,
               const ScanOutputOptions& options) {
  fs::create_directories(dir / "models");
  const std::string nii = options.gzip_images ? ".nii.gz" : ".nii";
  write_displacement_field(dir / ("field" + nii), r.pullback_field_mm);
  ItkTransformWriteOptions itk;
  itk.single_precision = options.itk_single_precision;
  write_itk_displacement_transform(dir / "field.h5", r.pullback_field_mm, itk);
  write_scalar_image(dir / ("warped_image" + nii), r.warped_t1);
  write_label_image(dir / ("warped_labels" + nii), r.warped_labels);
  for (const auto& [name, surface] : r.models) write_vtp(dir / "models" / (name + ".vtp"), surface);
  write_json(dir / "metrics.json", r.metrics);
  write_json(dir / "timings.json", r.timings);
  // The picture needs an intraop image to draw on; without one there is none.
  if (intraop_t1 && options.write_report) {
    const std::string png = scan_report_png(r, *intraop_t1, options.label_table, options.scan_id);
    std::ofstream out(dir / "report.png", std::ios::binary);
    out.write(png.data(), static_cast<std::streamsize>(png.size()));
    if (!out) throw InputError((dir / "report.png").string() + ": cannot write");
  }
}

}  // namespace

void write_scan_outputs(const ScanResult& result, const ImageF* intraop_t1, const fs::path& out_dir,
                        const ScanOutputOptions& options) {
  const fs::path temp = sibling_temp_dir(out_dir);
  try {
    if (out_dir.has_parent_path()) fs::create_directories(out_dir.parent_path());
    write_all(result, intraop_t1, temp, options);
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
