#include "dicom_input.h"

#include "image/dicom_series.h"
#include "image/nifti_io.h"

namespace brainshift::cli {

std::string dicom_series_nifti(const std::string& dir, const std::string& series_uid) {
  // The daemon bounds what it accepts itself; this only keeps a wrong folder
  // from filling the client's memory (2 GiB of float voxels).
  constexpr std::size_t kMaxBytes = std::size_t{2} << 30;
  return scalar_image_to_bytes(read_dicom_series(dir, series_uid, kMaxBytes), VoxelType::float32, true);
}

}  // namespace brainshift::cli
