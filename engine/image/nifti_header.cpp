// NIfTI-1 and NIfTI-2 headers -> one NiftiHeader; geometry from sform/qform.
#include "image/nifti_header.h"

#include <nifti/nifti1.h>
#include <nifti/nifti2.h>

#include <cmath>
#include <cstring>
#include <string>

#include "core/errors.h"
#include "image/nifti_io.h"

namespace brainshift::nifti_detail {
namespace {

static_assert(sizeof(nifti_1_header) == 348, "nifti1.h: the NIfTI-1 header is 348 bytes");
static_assert(sizeof(nifti_2_header) == 540, "nifti2.h: the NIfTI-2 header is 540 bytes");

[[noreturn]] void fail(std::string_view name, const std::string& what) {
  throw InputError(std::string(name) + ": " + what);
}

// Every multi-byte field of the two layouts (char fields have no byte order).
template <class H>
void swap_header(H& h) {
  swap_in_place(h.sizeof_hdr); swap_in_place(h.dim); swap_in_place(h.intent_p1);
  swap_in_place(h.intent_p2); swap_in_place(h.intent_p3); swap_in_place(h.intent_code);
  swap_in_place(h.datatype); swap_in_place(h.bitpix); swap_in_place(h.slice_start);
  swap_in_place(h.pixdim); swap_in_place(h.vox_offset); swap_in_place(h.scl_slope);
  swap_in_place(h.scl_inter); swap_in_place(h.slice_end); swap_in_place(h.cal_max);
  swap_in_place(h.cal_min); swap_in_place(h.slice_duration); swap_in_place(h.toffset);
  swap_in_place(h.qform_code); swap_in_place(h.sform_code); swap_in_place(h.quatern_b);
  swap_in_place(h.quatern_c); swap_in_place(h.quatern_d); swap_in_place(h.qoffset_x);
  swap_in_place(h.qoffset_y); swap_in_place(h.qoffset_z); swap_in_place(h.srow_x);
  swap_in_place(h.srow_y); swap_in_place(h.srow_z);
  if constexpr (sizeof(H) == sizeof(nifti_2_header)) {
    swap_in_place(h.slice_code); swap_in_place(h.xyzt_units);  // int32 in NIfTI-2, char in NIfTI-1
  } else {
    swap_in_place(h.extents); swap_in_place(h.session_error); swap_in_place(h.glmax); swap_in_place(h.glmin);
  }
}

// The fields the reader uses, widened to NIfTI-2's types.
template <class H>
NiftiHeader widen(const H& h) {
  NiftiHeader out;
  for (int d = 0; d < 8; ++d) {
    out.dim[d] = h.dim[d];
    out.pixdim[d] = h.pixdim[d];
  }
  out.datatype = h.datatype;
  out.intent_code = h.intent_code;
  out.vox_offset = static_cast<double>(h.vox_offset);
  out.scl_slope = h.scl_slope;
  out.scl_inter = h.scl_inter;
  out.qform_code = h.qform_code;
  out.sform_code = h.sform_code;
  out.quatern_b = h.quatern_b;
  out.quatern_c = h.quatern_c;
  out.quatern_d = h.quatern_d;
  out.qoffset_x = h.qoffset_x;
  out.qoffset_y = h.qoffset_y;
  out.qoffset_z = h.qoffset_z;
  for (int c = 0; c < 4; ++c) {
    out.srow[0][c] = h.srow_x[c];
    out.srow[1][c] = h.srow_y[c];
    out.srow[2][c] = h.srow_z[c];
  }
  return out;
}

// "n+1\0" / "n+2\0" single file; "ni1\0" / "ni2\0" is the two-file form.
void check_magic(const char* magic, int version, std::string_view name) {
  const std::string v = std::to_string(version);
  if (std::memcmp(magic, ("ni" + v).c_str(), 4) == 0)
    fail(name, "two-file NIfTI-" + v + " (.hdr/.img) is not supported; convert to a single .nii");
  if (std::memcmp(magic, ("n+" + v).c_str(), 4) != 0) fail(name, "not a NIfTI-" + v + " file (bad magic)");
  // Bytes 4..7 of the NIfTI-2 magic are "\r\n\032\n", so that a text-mode
  // transfer (CR/LF rewriting) is detected instead of shifting every voxel.
  // Zeros are accepted too: niftilib's own nifti_convert_nim2n2hdr leaves
  // them zero (nibabel accepts both as well).
  if (version == 2 && std::memcmp(magic + 4, "\r\n\032\n", 4) != 0 && std::memcmp(magic + 4, "\0\0\0\0", 4) != 0)
    fail(name, "NIfTI-2 magic is damaged (bytes 4..7 are neither \\r\\n\\032\\n nor zero): the file was "
               "altered, e.g. by a text-mode transfer");
}

// H is nifti_1_header or nifti_2_header.
template <class H>
NiftiHeader decode_as(const char* bytes, bool swapped, std::string_view name) {
  H h;
  std::memcpy(&h, bytes, sizeof h);
  if (swapped) swap_header(h);
  const int version = sizeof(H) == sizeof(nifti_2_header) ? 2 : 1;
  check_magic(h.magic, version, name);
  NiftiHeader out = widen(h);
  out.version = version;
  out.header_bytes = sizeof h;
  out.swapped = swapped;
  return out;
}

Eigen::Matrix4d quatern_to_affine(const NiftiHeader& h) {
  double b = h.quatern_b, c = h.quatern_c, d = h.quatern_d;
  const double a2 = 1.0 - (b * b + c * c + d * d);
  double a = 0.0;
  if (a2 < 1e-7) {  // a is tiny: renormalise (b,c,d) like niftilib
    const double n = std::sqrt(b * b + c * c + d * d);
    b /= n; c /= n; d /= n;
  } else {
    a = std::sqrt(a2);
  }
  Eigen::Matrix3d r;
  r << a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c),
      2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b),
      2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - c * c - b * b;
  const double qfac = h.pixdim[0] < 0 ? -1.0 : 1.0;
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topLeftCorner<3, 3>() = r * Eigen::Vector3d(h.pixdim[1], h.pixdim[2], qfac * h.pixdim[3]).asDiagonal();
  m.topRightCorner<3, 1>() = Eigen::Vector3d(h.qoffset_x, h.qoffset_y, h.qoffset_z);
  return m;
}

void require_positive_pixdim(const NiftiHeader& h, std::string_view name) {
  for (int d = 1; d <= 3; ++d)
    if (!(h.pixdim[d] > 0.0) || !std::isfinite(h.pixdim[d]))
      fail(name, "voxel size pixdim[" + std::to_string(d) + "] = " + std::to_string(h.pixdim[d]) +
                     " is not positive (and there is no sform to give the geometry)");
}

}  // namespace

NiftiHeader read_header(ByteStream& stream, std::string_view name) {
  char bytes[sizeof(nifti_2_header)];
  const std::size_t got = stream.read(bytes, sizeof(nifti_1_header));
  if (got < sizeof(nifti_1_header))
    fail(name, "truncated or not a NIfTI file: only " + std::to_string(got) + " bytes, a NIfTI-1 header needs 348");
  std::int32_t size = 0;
  std::memcpy(&size, bytes, 4);
  std::int32_t swapped_size = size;
  swap_in_place(swapped_size);
  const bool swapped = size != 348 && size != 540;
  if (swapped) size = swapped_size;
  if (size == 348) return decode_as<nifti_1_header>(bytes, swapped, name);
  if (size != 540) fail(name, "not a NIfTI-1 or NIfTI-2 file (sizeof_hdr is neither 348 nor 540)");
  const std::size_t rest = sizeof(nifti_2_header) - sizeof(nifti_1_header);
  const std::size_t more = stream.read(bytes + sizeof(nifti_1_header), rest);
  if (more < rest)
    fail(name, "truncated NIfTI-2 header: only " + std::to_string(got + more) + " bytes, a header needs 540");
  return decode_as<nifti_2_header>(bytes, swapped, name);
}

std::size_t bytes_per_voxel(std::int32_t datatype) {
  switch (datatype) {
    case DT_UINT8: case DT_INT8: return 1;
    case DT_INT16: case DT_UINT16: return 2;
    case DT_INT32: case DT_UINT32: case DT_FLOAT32: return 4;
    case DT_FLOAT64: case DT_INT64: case DT_UINT64: return 8;
    default: return 0;
  }
}

Eigen::Matrix4d world_from_voxel_of(const NiftiHeader& h, std::string_view name) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  if (h.sform_code > 0) {
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) m(r, c) = h.srow[r][c];
  } else if (h.qform_code > 0) {
    require_positive_pixdim(h, name);
    m = quatern_to_affine(h);
  } else {
    require_positive_pixdim(h, name);
    m.diagonal().head<3>() = Eigen::Vector3d(h.pixdim[1], h.pixdim[2], h.pixdim[3]);
  }
  validate_world_from_voxel(m, name);
  return m;
}

}  // namespace brainshift::nifti_detail

namespace brainshift {

void validate_world_from_voxel(const Eigen::Matrix4d& a, std::string_view what) {
  if (!a.allFinite()) nifti_detail::fail(what, "world_from_voxel affine has NaN/Inf entries");
  if ((a.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).cwiseAbs().maxCoeff() > 1e-9)
    nifti_detail::fail(what, "world_from_voxel affine's last row is not 0 0 0 1");
  const Eigen::Matrix3d m = a.topLeftCorner<3, 3>();
  const Eigen::Vector3d sp = m.colwise().norm();
  for (int d = 0; d < 3; ++d)
    if (!(sp[d] >= 0.01 && sp[d] <= 100.0))
      nifti_detail::fail(what, "voxel size " + std::to_string(sp[d]) + " mm along axis " + std::to_string(d) +
                                   " is outside [0.01, 100] mm");
  // Relative to the voxel volume, so small voxels are not mistaken for singular.
  if (std::abs(m.determinant()) < 1e-6 * sp.prod())
    nifti_detail::fail(what, "world_from_voxel affine is singular (voxel axes are collinear)");
}

}  // namespace brainshift
