#include "format_conversion.h"

#include <filesystem>
#include <iostream>

#include "label_table_file.h"
#include "image/dicom_series.h"
#include "image/nifti_io.h"
#include "image/nrrd_io.h"

namespace brainshift::cli {
namespace {
// The daemon bounds what it accepts itself; this only keeps a wrong input
// from filling the client's memory (2 GiB of voxels).
constexpr std::size_t kMaxBytes = std::size_t{2} << 30;
}  // namespace

DicomNifti dicom_series_nifti(const std::string& dir, const std::string& series_uid) {
  DicomNifti out;
  out.nifti = scalar_image_to_bytes(read_dicom_series(dir, series_uid, kMaxBytes, &out.patient_id), VoxelType::float32,
                                    true);
  return out;
}

std::string nrrd_nifti(const std::string& path, bool labels) {
  if (!labels) return scalar_image_to_bytes(read_nrrd_scalar(path, kMaxBytes), VoxelType::float32, true);
  if (is_slicer_segmentation_path(path))
    return label_image_to_bytes(read_slicer_segmentation(path, config::default_label_table(), kMaxBytes), true);
  return label_image_to_bytes(read_nrrd_labels(path, kMaxBytes), true);
}

void write_nrrd_outputs(const std::string& dir) {
  namespace fs = std::filesystem;
  const fs::path d = dir;
  auto done = [](const fs::path& p) { std::cout << p.string() << '\n'; };
  if (fs::is_regular_file(d / "field.nii.gz")) {
    write_nrrd_displacement(d / "field.nrrd", read_vector_image(d / "field.nii.gz"));
    done(d / "field.nrrd");
  }
  if (fs::is_regular_file(d / "warped_image.nii.gz")) {
    write_nrrd_scalar(d / "warped_image.nrrd", read_scalar_image(d / "warped_image.nii.gz", kMaxBytes));
    done(d / "warped_image.nrrd");
  }
  if (fs::is_regular_file(d / "warped_labels.nii.gz")) {
    write_nrrd_labels(d / "warped_labels.nrrd", read_label_image(d / "warped_labels.nii.gz", kMaxBytes));
    done(d / "warped_labels.nrrd");
  }
}

}  // namespace brainshift::cli
