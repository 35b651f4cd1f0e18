// NIfTI-1 writers (the reference layout nifti_1_header from nifti1.h). We
// write NIfTI-1 only: every tool our users pair us with (ITK, Slicer, FSL,
// nibabel) reads it, and our grids fit its int16 dims.
#include <nifti/nifti1.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <limits>

#include "core/errors.h"
#include "core/gzip.h"
#include "image/nifti_gzip.h"
#include "image/nifti_header.h"
#include "image/nifti_io.h"

namespace brainshift {
namespace {

constexpr std::size_t kDataOffset = sizeof(nifti_1_header) + 4;  // header + 4-byte extension flag

[[noreturn]] void fail(std::string_view name, const std::string& what) {
  throw InputError(std::string(name) + ": " + what);
}

bool is_rotation_times_scale(const Eigen::Matrix3d& m) {
  const Eigen::Vector3d norms = m.colwise().norm();
  const Eigen::Matrix3d r = m * norms.cwiseInverse().asDiagonal();
  return (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() < 1e-5;
}

void set_qform(nifti_1_header& h, const Eigen::Matrix4d& a) {
  const Eigen::Matrix3d m = a.topLeftCorner<3, 3>();
  const Eigen::Vector3d norms = m.colwise().norm();
  Eigen::Matrix3d r = m * norms.cwiseInverse().asDiagonal();
  double qfac = 1.0;
  if (r.determinant() < 0) {  // NIfTI stores a left-handed frame as qfac = -1 on the k axis
    qfac = -1.0;
    r.col(2) *= -1.0;
  }
  Eigen::Quaterniond q(r);
  q.normalize();
  if (q.w() < 0) q.coeffs() *= -1.0;
  h.quatern_b = static_cast<float>(q.x());
  h.quatern_c = static_cast<float>(q.y());
  h.quatern_d = static_cast<float>(q.z());
  h.qoffset_x = static_cast<float>(a(0, 3));
  h.qoffset_y = static_cast<float>(a(1, 3));
  h.qoffset_z = static_cast<float>(a(2, 3));
  h.pixdim[0] = static_cast<float>(qfac);
  h.qform_code = NIFTI_XFORM_SCANNER_ANAT;
}

nifti_1_header make_header(const Grid3& g, std::int16_t datatype, int ncomp, std::string_view what) {
  for (int d = 0; d < 3; ++d)
    if (g.dims[d] <= 0 || g.dims[d] > 32767)
      fail(what, "cannot write dimension " + std::to_string(g.dims[d]) + " (NIfTI-1 allows 1..32767)");
  validate_world_from_voxel(g.world_from_voxel, what);
  nifti_1_header h{};
  h.sizeof_hdr = sizeof(nifti_1_header);
  h.regular = 'r';
  h.dim[0] = ncomp > 1 ? 5 : 3;
  for (int d = 0; d < 3; ++d) h.dim[d + 1] = static_cast<std::int16_t>(g.dims[d]);
  for (int d = 4; d < 8; ++d) h.dim[d] = 1;
  h.dim[5] = static_cast<std::int16_t>(ncomp);
  h.datatype = datatype;
  h.bitpix = static_cast<std::int16_t>(8 * nifti_detail::bytes_per_voxel(datatype));
  const Eigen::Vector3d sp = g.spacing_mm();
  h.pixdim[0] = 1.f;
  for (int d = 0; d < 3; ++d) h.pixdim[d + 1] = static_cast<float>(sp[d]);
  for (int d = 4; d < 8; ++d) h.pixdim[d] = 1.f;
  h.vox_offset = static_cast<float>(kDataOffset);
  h.scl_slope = 1.f;
  h.xyzt_units = NIFTI_UNITS_MM | NIFTI_UNITS_SEC;
  std::memcpy(h.descrip, "brainshift", 10);
  const Eigen::Matrix4d& a = g.world_from_voxel;
  for (int c = 0; c < 4; ++c) {
    h.srow_x[c] = static_cast<float>(a(0, c));
    h.srow_y[c] = static_cast<float>(a(1, c));
    h.srow_z[c] = static_cast<float>(a(2, c));
  }
  h.sform_code = NIFTI_XFORM_SCANNER_ANAT;
  if (is_rotation_times_scale(a.topLeftCorner<3, 3>())) set_qform(h, a);
  std::memcpy(h.magic, "n+1\0", 4);
  return h;
}

std::string assemble(const nifti_1_header& h, const std::string& data, bool gzip) {
  std::string raw(kDataOffset, '\0');
  std::memcpy(raw.data(), &h, sizeof h);
  raw += data;
  return gzip ? gzip_bytes(raw) : raw;
}

template <class T>
void append_pod(std::string& out, T v) {
  const auto old = out.size();
  out.resize(old + sizeof(T));
  std::memcpy(out.data() + old, &v, sizeof(T));
}

// Encodes floats as uint8/int16; exact when the data are integers in range.
template <class T>
std::string encode_integer(const ImageF& img, nifti_1_header& h) {
  const auto [mn_it, mx_it] = std::minmax_element(img.voxels.begin(), img.voxels.end());
  const double mn = *mn_it, mx = *mx_it;
  const double tmin = std::numeric_limits<T>::min(), tmax = std::numeric_limits<T>::max();
  const bool integral = std::all_of(img.voxels.begin(), img.voxels.end(),
                                    [](float v) { return v == std::nearbyint(v); });
  double slope = 1.0, inter = 0.0;
  if (!(integral && mn >= tmin && mx <= tmax)) {
    slope = mx > mn ? (mx - mn) / (tmax - tmin) : 1.0;
    inter = mn - tmin * slope;
  }
  h.scl_slope = static_cast<float>(slope);
  h.scl_inter = static_cast<float>(inter);
  std::string data;
  data.reserve(img.voxels.size() * sizeof(T));
  for (float v : img.voxels) {
    const double q = std::clamp(std::nearbyint((v - inter) / slope), tmin, tmax);
    append_pod(data, static_cast<T>(q));
  }
  return data;
}

void check_size(const Grid3& g, std::size_t n, std::string_view what) {
  if (n != g.voxel_count())
    fail(what, "voxel buffer has " + std::to_string(n) + " values but the grid has " +
                   std::to_string(g.voxel_count()));
}

void check_finite(const ImageF& img, std::string_view what) {
  const auto bad = std::count_if(img.voxels.begin(), img.voxels.end(), [](float v) { return !std::isfinite(v); });
  if (bad > 0) fail(what, std::to_string(bad) + " voxels are NaN or Inf; refusing to write");
}

std::string scalar_bytes_named(const ImageF& image, VoxelType type, bool gzip, std::string_view what) {
  check_size(image.grid, image.voxels.size(), what);
  check_finite(image, what);
  if (type == VoxelType::float32) {
    nifti_1_header h = make_header(image.grid, DT_FLOAT32, 1, what);
    std::string data(image.voxels.size() * sizeof(float), '\0');
    std::memcpy(data.data(), image.voxels.data(), data.size());
    return assemble(h, data, gzip);
  }
  nifti_1_header h = make_header(image.grid, type == VoxelType::uint8 ? DT_UINT8 : DT_INT16, 1, what);
  const std::string data = type == VoxelType::uint8 ? encode_integer<std::uint8_t>(image, h)
                                                    : encode_integer<std::int16_t>(image, h);
  return assemble(h, data, gzip);
}

std::string label_bytes_named(const LabelImage& labels, bool gzip, std::string_view what) {
  check_size(labels.grid, labels.voxels.size(), what);
  const std::uint16_t mx = labels.voxels.empty() ? 0 : *std::max_element(labels.voxels.begin(), labels.voxels.end());
  if (mx > 32767) fail(what, "label " + std::to_string(mx) + " does not fit int16 (max 32767)");
  const bool small = mx <= 255;
  nifti_1_header h = make_header(labels.grid, small ? DT_UINT8 : DT_INT16, 1, what);
  std::string data;
  data.reserve(labels.voxels.size() * (small ? 1 : 2));
  for (std::uint16_t v : labels.voxels) {
    if (small) append_pod(data, static_cast<std::uint8_t>(v));
    else append_pod(data, static_cast<std::int16_t>(v));
  }
  return assemble(h, data, gzip);
}

std::string field_bytes_named(const VectorImage3& field, bool gzip, std::string_view what) {
  check_size(field.grid, field.vectors.size(), what);
  nifti_1_header h = make_header(field.grid, DT_FLOAT32, 3, what);
  h.intent_code = NIFTI_INTENT_DISPVECT;
  std::memcpy(h.intent_name, "displacement", 12);
  const std::size_t n = field.vectors.size();
  std::string data(3 * n * sizeof(float), '\0');
  auto* out = reinterpret_cast<float*>(data.data());
  std::size_t bad = 0;
  for (int c = 0; c < 3; ++c)
    for (std::size_t i = 0; i < n; ++i) {
      out[c * n + i] = field.vectors[i][c];
      bad += !std::isfinite(field.vectors[i][c]);
    }
  if (bad > 0) fail(what, std::to_string(bad) + " vector components are NaN or Inf; refusing to write");
  return assemble(h, data, gzip);
}

bool wants_gzip(const std::filesystem::path& path) { return path.extension() == ".gz"; }

void write_file(const std::filesystem::path& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) fail(path.string(), "cannot open for writing");
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  out.close();
  if (!out) fail(path.string(), "write failed (disk full?)");
}

}  // namespace

void write_scalar_image(const std::filesystem::path& path, const ImageF& image, VoxelType type) {
  write_file(path, scalar_bytes_named(image, type, wants_gzip(path), path.string()));
}
void write_label_image(const std::filesystem::path& path, const LabelImage& labels) {
  write_file(path, label_bytes_named(labels, wants_gzip(path), path.string()));
}
void write_displacement_field(const std::filesystem::path& path, const VectorImage3& field_mm) {
  write_file(path, field_bytes_named(field_mm, wants_gzip(path), path.string()));
}

std::string scalar_image_to_bytes(const ImageF& image, VoxelType type, bool gzip) {
  return scalar_bytes_named(image, type, gzip, "scalar image");
}
std::string label_image_to_bytes(const LabelImage& labels, bool gzip) {
  return label_bytes_named(labels, gzip, "label image");
}
std::string displacement_field_to_bytes(const VectorImage3& field_mm, bool gzip) {
  return field_bytes_named(field_mm, gzip, "displacement field");
}

}  // namespace brainshift
