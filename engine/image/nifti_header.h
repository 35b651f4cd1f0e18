#pragma once
// The NIfTI header as the reader uses it (internal to engine/image): NIfTI-1
// (348 bytes) and NIfTI-2 (540 bytes) are both decoded into one struct with
// NIfTI-2's wider types, in native byte order. The byte layouts are the
// reference ones, nifti1.h and nifti2.h from Debian's libnifti2-dev.
#include <Eigen/Dense>

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "image/nifti_gzip.h"

namespace brainshift::nifti_detail {

struct NiftiHeader {
  int version = 1;               // 1 or 2
  std::size_t header_bytes = 0;  // 348 or 540: the smallest legal vox_offset
  bool swapped = false;          // the file is in the other byte order
  std::array<std::int64_t, 8> dim{};
  std::int32_t datatype = 0;
  std::int32_t intent_code = 0;
  std::array<double, 8> pixdim{};
  double vox_offset = 0;  // a float in NIfTI-1, an int64 in NIfTI-2
  double scl_slope = 0, scl_inter = 0;
  std::int32_t qform_code = 0, sform_code = 0;
  double quatern_b = 0, quatern_c = 0, quatern_d = 0;
  double qoffset_x = 0, qoffset_y = 0, qoffset_z = 0;
  std::array<std::array<double, 4>, 3> srow{};
};

// Reads the header from the start of the stream (348 bytes, and 192 more for
// NIfTI-2); throws InputError naming `name` for anything that is not a
// single-file NIfTI-1 or NIfTI-2 header.
NiftiHeader read_header(ByteStream& stream, std::string_view name);

// Bytes per voxel of a supported datatype, 0 for any other.
std::size_t bytes_per_voxel(std::int32_t datatype);

// sform when sform_code > 0, else qform when qform_code > 0, else
// diag(pixdim[1..3]); validated (validate_world_from_voxel).
Eigen::Matrix4d world_from_voxel_of(const NiftiHeader& h, std::string_view name);

template <class T>
void swap_in_place(T& v) {
  auto* p = reinterpret_cast<unsigned char*>(&v);
  std::reverse(p, p + sizeof(T));
}

template <class T, std::size_t N>
void swap_in_place(T (&a)[N]) {
  for (auto& v : a) swap_in_place(v);
}

}  // namespace brainshift::nifti_detail
