// NIfTI-1 reader/writer. The 348-byte header is decoded here; voxel data are
// read from a raw or gzip stream whose decompressed size is bounded before any
// voxel buffer is allocated.
#include "image/nifti_io.h"

#include <zlib.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <functional>
#include <limits>
#include <sstream>

#include "core/errors.h"

namespace brainshift {
namespace {

// Layout of the NIfTI-1 header (nifti1.h); naturally aligned, no padding.
struct Nifti1Header {
  std::int32_t sizeof_hdr;
  char data_type[10];
  char db_name[18];
  std::int32_t extents;
  std::int16_t session_error;
  char regular;
  char dim_info;
  std::int16_t dim[8];
  float intent_p1, intent_p2, intent_p3;
  std::int16_t intent_code, datatype, bitpix, slice_start;
  float pixdim[8];
  float vox_offset, scl_slope, scl_inter;
  std::int16_t slice_end;
  char slice_code, xyzt_units;
  float cal_max, cal_min, slice_duration, toffset;
  std::int32_t glmax, glmin;
  char descrip[80];
  char aux_file[24];
  std::int16_t qform_code, sform_code;
  float quatern_b, quatern_c, quatern_d, qoffset_x, qoffset_y, qoffset_z;
  float srow_x[4], srow_y[4], srow_z[4];
  char intent_name[16];
  char magic[4];
};
static_assert(sizeof(Nifti1Header) == 348, "NIfTI-1 header must be 348 bytes");

constexpr std::size_t kHeaderBytes = 348;
constexpr std::size_t kDataOffset = 352;  // header + 4-byte extension flag
constexpr std::int16_t kXformScannerAnat = 1;
constexpr std::int16_t kIntentDispVect = 1006;

enum : std::int16_t {
  DT_UINT8 = 2, DT_INT16 = 4, DT_INT32 = 8, DT_FLOAT32 = 16, DT_FLOAT64 = 64,
  DT_INT8 = 256, DT_UINT16 = 512, DT_UINT32 = 768, DT_INT64 = 1024, DT_UINT64 = 1280
};

std::size_t bytes_per_voxel(std::int16_t datatype) {
  switch (datatype) {
    case DT_UINT8: case DT_INT8: return 1;
    case DT_INT16: case DT_UINT16: return 2;
    case DT_INT32: case DT_UINT32: case DT_FLOAT32: return 4;
    case DT_FLOAT64: case DT_INT64: case DT_UINT64: return 8;
    default: return 0;
  }
}

[[noreturn]] void fail(std::string_view name, const std::string& what) {
  throw InputError(std::string(name) + ": " + what);
}

template <class T>
void swap_in_place(T& v) {
  auto* p = reinterpret_cast<unsigned char*>(&v);
  std::reverse(p, p + sizeof(T));
}

template <class T, std::size_t N>
void swap_in_place(T (&a)[N]) {
  for (auto& v : a) swap_in_place(v);
}

void swap_header(Nifti1Header& h) {
  swap_in_place(h.sizeof_hdr); swap_in_place(h.extents); swap_in_place(h.session_error);
  swap_in_place(h.dim); swap_in_place(h.intent_p1); swap_in_place(h.intent_p2);
  swap_in_place(h.intent_p3); swap_in_place(h.intent_code); swap_in_place(h.datatype);
  swap_in_place(h.bitpix); swap_in_place(h.slice_start); swap_in_place(h.pixdim);
  swap_in_place(h.vox_offset); swap_in_place(h.scl_slope); swap_in_place(h.scl_inter);
  swap_in_place(h.slice_end); swap_in_place(h.cal_max); swap_in_place(h.cal_min);
  swap_in_place(h.slice_duration); swap_in_place(h.toffset); swap_in_place(h.glmax);
  swap_in_place(h.glmin); swap_in_place(h.qform_code); swap_in_place(h.sform_code);
  swap_in_place(h.quatern_b); swap_in_place(h.quatern_c); swap_in_place(h.quatern_d);
  swap_in_place(h.qoffset_x); swap_in_place(h.qoffset_y); swap_in_place(h.qoffset_z);
  swap_in_place(h.srow_x); swap_in_place(h.srow_y); swap_in_place(h.srow_z);
}

// Sequential reader over raw or gzip-compressed bytes.
class ByteStream {
 public:
  ByteStream(std::string_view bytes, std::string_view name) : in_(bytes), name_(name) {
    gzip_ = bytes.size() >= 2 && static_cast<unsigned char>(bytes[0]) == 0x1f &&
            static_cast<unsigned char>(bytes[1]) == 0x8b;
    if (gzip_) {
      std::memset(&zs_, 0, sizeof(zs_));
      if (inflateInit2(&zs_, 15 + 32) != Z_OK) fail(name_, "cannot initialise zlib");
      zs_.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(in_.data()));
      zs_.avail_in = static_cast<uInt>(std::min<std::size_t>(in_.size(), kChunk));
      consumed_ = zs_.avail_in;
    }
  }
  ~ByteStream() {
    if (gzip_) inflateEnd(&zs_);
  }
  ByteStream(const ByteStream&) = delete;
  ByteStream& operator=(const ByteStream&) = delete;

  // Reads up to n bytes into dst; returns how many were available.
  std::size_t read(char* dst, std::size_t n) {
    if (!gzip_) {
      const std::size_t got = std::min(n, in_.size() - pos_);
      std::memcpy(dst, in_.data() + pos_, got);
      pos_ += got;
      return got;
    }
    return inflate_into(dst, n);
  }

 private:
  static constexpr std::size_t kChunk = 1u << 30;  // zlib counts in 32-bit uInt

  std::size_t inflate_into(char* dst, std::size_t n) {
    std::size_t got = 0;
    while (got < n && !finished_) {
      zs_.next_out = reinterpret_cast<Bytef*>(dst + got);
      zs_.avail_out = static_cast<uInt>(std::min(n - got, kChunk));
      const uInt before = zs_.avail_out;
      const int rc = inflate(&zs_, Z_NO_FLUSH);
      got += before - zs_.avail_out;
      if (zs_.avail_in == 0 && consumed_ < in_.size()) refill();
      if (rc == Z_STREAM_END) {
        // Concatenated gzip members are legal; continue with the next one.
        if (zs_.avail_in == 0 && consumed_ >= in_.size()) { finished_ = true; break; }
        inflateReset(&zs_);
        continue;
      }
      if (rc == Z_BUF_ERROR) {  // no progress possible: input exhausted mid-stream
        if (zs_.avail_in == 0 && consumed_ >= in_.size()) { finished_ = true; break; }
        continue;
      }
      if (rc != Z_OK) fail(name_, std::string("corrupt gzip data (") + (zs_.msg ? zs_.msg : "zlib error") + ")");
    }
    return got;
  }
  void refill() {
    zs_.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(in_.data() + consumed_));
    zs_.avail_in = static_cast<uInt>(std::min(in_.size() - consumed_, kChunk));
    consumed_ += zs_.avail_in;
  }

  std::string_view in_;
  std::string_view name_;
  bool gzip_ = false;
  bool finished_ = false;
  std::size_t pos_ = 0;
  std::size_t consumed_ = 0;
  z_stream zs_{};
};

struct RawNifti {
  Nifti1Header hdr{};
  bool swapped = false;
  std::array<std::int64_t, 7> dims{1, 1, 1, 1, 1, 1, 1};
  std::size_t voxel_count = 0;  // product of all dims
  std::string data;             // exactly voxel_count * bytes_per_voxel bytes
};

Nifti1Header read_header(ByteStream& stream, std::string_view name, bool& swapped) {
  Nifti1Header h{};
  const std::size_t got = stream.read(reinterpret_cast<char*>(&h), kHeaderBytes);
  if (got < kHeaderBytes)
    fail(name, "truncated or not a NIfTI-1 file: only " + std::to_string(got) + " bytes, a header needs 348");
  swapped = false;
  if (h.sizeof_hdr != 348) {
    std::int32_t s = h.sizeof_hdr;
    swap_in_place(s);
    if (s != 348) fail(name, "not a NIfTI-1 file (sizeof_hdr is not 348)");
    swap_header(h);
    swapped = true;
  }
  if (std::memcmp(h.magic, "ni1\0", 4) == 0)
    fail(name, "two-file NIfTI (.hdr/.img) is not supported; convert to a single .nii");
  if (std::memcmp(h.magic, "n+1\0", 4) != 0) fail(name, "not a NIfTI-1 file (bad magic)");
  return h;
}

RawNifti decode(std::string_view bytes, std::string_view name, std::size_t max_bytes) {
  ByteStream stream(bytes, name);
  RawNifti raw;
  raw.hdr = read_header(stream, name, raw.swapped);
  const Nifti1Header& h = raw.hdr;
  if (h.dim[0] < 1 || h.dim[0] > 7) fail(name, "invalid dim[0] = " + std::to_string(h.dim[0]));
  std::size_t nvox = 1;
  for (int d = 1; d <= h.dim[0]; ++d) {
    if (h.dim[d] <= 0) fail(name, "zero-sized or negative dimension dim[" + std::to_string(d) + "] = " + std::to_string(h.dim[d]));
    raw.dims[d - 1] = h.dim[d];
    nvox *= static_cast<std::size_t>(h.dim[d]);  // <= 32767^7 needs a check below
  }
  const std::size_t bpv = bytes_per_voxel(h.datatype);
  if (bpv == 0) fail(name, "unsupported NIfTI datatype " + std::to_string(h.datatype));
  if (!(h.vox_offset >= static_cast<float>(kHeaderBytes)) || h.vox_offset > 1e9f)
    fail(name, "invalid vox_offset " + std::to_string(h.vox_offset));
  const auto offset = static_cast<std::size_t>(h.vox_offset);
  // Guard the multiplication: seven dims of 32767 overflow 64 bits.
  long double total = static_cast<long double>(offset);
  long double voxels = 1;
  for (int d = 0; d < 7; ++d) voxels *= static_cast<long double>(raw.dims[d]);
  total += voxels * bpv;
  if (total > static_cast<long double>(max_bytes))
    fail(name, "header claims " + std::to_string(static_cast<double>(total)) +
                   " decompressed bytes, more than the limit of " + std::to_string(max_bytes));
  raw.voxel_count = nvox;

  // Skipped in small pieces: a tiny file claiming a huge vox_offset must not
  // make us allocate the claim.
  std::string skip(std::min<std::size_t>(offset - kHeaderBytes, 64 * 1024), '\0');
  for (std::size_t left = offset - kHeaderBytes; left > 0;) {
    const std::size_t n = std::min(left, skip.size());
    if (stream.read(skip.data(), n) < n)
      fail(name, "truncated: file ends before the voxel data (vox_offset " + std::to_string(offset) + ")");
    left -= n;
  }
  // Grow the buffer as data actually arrive, so that a file whose header claims
  // far more than it holds fails as truncated instead of allocating the claim.
  const std::size_t want = nvox * bpv;
  std::size_t got = 0;
  while (got < want) {
    const std::size_t next = std::min(want, std::max<std::size_t>(std::size_t{64} << 20, 2 * got));
    raw.data.resize(next);
    const std::size_t n = stream.read(raw.data.data() + got, next - got);
    got += n;
    if (got < next) break;
  }
  if (got < want)
    fail(name, "truncated: header promises " + std::to_string(want) + " bytes of voxel data, found only " +
                   std::to_string(got));
  return raw;
}

// Calls fn(index, value) for every voxel as double, byte order fixed.
template <class Fn>
void for_each_value(const RawNifti& raw, std::size_t first, std::size_t count, Fn&& fn) {
  auto run = [&](auto tag) {
    using T = decltype(tag);
    const char* base = raw.data.data() + first * sizeof(T);
    for (std::size_t i = 0; i < count; ++i) {
      T v;
      std::memcpy(&v, base + i * sizeof(T), sizeof(T));
      if constexpr (sizeof(T) > 1) {
        if (raw.swapped) swap_in_place(v);
      }
      fn(i, static_cast<double>(v));
    }
  };
  switch (raw.hdr.datatype) {
    case DT_UINT8: run(std::uint8_t{}); break;
    case DT_INT8: run(std::int8_t{}); break;
    case DT_UINT16: run(std::uint16_t{}); break;
    case DT_INT16: run(std::int16_t{}); break;
    case DT_UINT32: run(std::uint32_t{}); break;
    case DT_INT32: run(std::int32_t{}); break;
    case DT_UINT64: run(std::uint64_t{}); break;
    case DT_INT64: run(std::int64_t{}); break;
    case DT_FLOAT32: run(float{}); break;
    case DT_FLOAT64: run(double{}); break;
    default: break;  // rejected in decode()
  }
}

// NIfTI: scl_slope == 0 means "no scaling". A non-finite slope is treated the
// same way (nibabel does too); a non-finite intercept with a real slope is an error.
std::pair<double, double> scaling(const RawNifti& raw, std::string_view name) {
  const double slope = raw.hdr.scl_slope, inter = raw.hdr.scl_inter;
  if (slope == 0.0 || !std::isfinite(slope)) return {1.0, 0.0};
  if (!std::isfinite(inter)) fail(name, "non-finite scl_inter");
  return {slope, inter};
}

Eigen::Matrix4d quatern_to_affine(const Nifti1Header& h) {
  double b = h.quatern_b, c = h.quatern_c, d = h.quatern_d;
  double a2 = 1.0 - (b * b + c * c + d * d);
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

void require_positive_pixdim(const Nifti1Header& h, std::string_view name) {
  for (int d = 1; d <= 3; ++d)
    if (!(h.pixdim[d] > 0.f) || !std::isfinite(h.pixdim[d]))
      fail(name, "voxel size pixdim[" + std::to_string(d) + "] = " + std::to_string(h.pixdim[d]) +
                     " is not positive (and there is no sform to give the geometry)");
}

Eigen::Matrix4d world_from_voxel_of(const Nifti1Header& h, std::string_view name) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  if (h.sform_code > 0) {
    for (int c = 0; c < 4; ++c) {
      m(0, c) = h.srow_x[c];
      m(1, c) = h.srow_y[c];
      m(2, c) = h.srow_z[c];
    }
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

Grid3 grid_of(const RawNifti& raw, std::string_view name) {
  Grid3 g;
  for (int d = 0; d < 3; ++d) g.dims[d] = static_cast<int>(raw.dims[d]);
  g.world_from_voxel = world_from_voxel_of(raw.hdr, name);
  return g;
}

void require_3d(const RawNifti& raw, std::string_view name) {
  for (int d = 3; d < 7; ++d)
    if (raw.dims[d] != 1)
      fail(name, "expected a 3-D image but dim[" + std::to_string(d + 1) + "] = " + std::to_string(raw.dims[d]) +
                     " (4-D/5-D data)");
}

ImageF to_scalar(const RawNifti& raw, std::string_view name) {
  require_3d(raw, name);
  ImageF img(grid_of(raw, name));
  const auto [slope, inter] = scaling(raw, name);
  float* out = img.voxels.data();
  std::size_t bad = 0;
  for_each_value(raw, 0, raw.voxel_count, [&](std::size_t i, double v) {
    const float f = static_cast<float>(v * slope + inter);
    bad += !std::isfinite(f);
    out[i] = f;
  });
  if (bad > 0) fail(name, std::to_string(bad) + " voxels are NaN or Inf");
  return img;
}

LabelImage to_labels(const RawNifti& raw, std::string_view name) {
  require_3d(raw, name);
  LabelImage img(grid_of(raw, name));
  const auto [slope, inter] = scaling(raw, name);
  std::uint16_t* out = img.voxels.data();
  std::size_t bad = 0;
  double first_bad = 0;
  for_each_value(raw, 0, raw.voxel_count, [&](std::size_t i, double v) {
    const double s = v * slope + inter;
    if (!(s >= 0.0 && s <= 65535.0) || s != std::floor(s)) {
      if (bad++ == 0) first_bad = s;
      return;
    }
    out[i] = static_cast<std::uint16_t>(s);
  });
  if (bad > 0)
    fail(name, "not a label image: " + std::to_string(bad) + " voxels are not integers in 0..65535 (e.g. " +
                   std::to_string(first_bad) + ")");
  return img;
}

VectorImage3 to_vectors(const RawNifti& raw, std::string_view name) {
  if (raw.dims[3] != 1 || raw.dims[4] != 3 || raw.dims[5] != 1 || raw.dims[6] != 1)
    fail(name, "expected a vector field with dims (nx,ny,nz,1,3)");
  VectorImage3 field(grid_of(raw, name));
  const auto [slope, inter] = scaling(raw, name);
  const std::size_t n = field.grid.voxel_count();
  std::size_t bad = 0;
  for (int c = 0; c < 3; ++c) {
    for_each_value(raw, c * n, n, [&](std::size_t i, double v) {
      const float f = static_cast<float>(v * slope + inter);
      bad += !std::isfinite(f);
      field.vectors[i][c] = f;
    });
  }
  if (bad > 0) fail(name, std::to_string(bad) + " vector components are NaN or Inf");
  return field;
}

std::string read_file_bytes(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) fail(path.string(), "file not found (or not a regular file)");
  std::ifstream in(path, std::ios::binary);
  if (!in) fail(path.string(), "cannot open file");
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) fail(path.string(), "read error");
  return std::move(ss).str();
}

// ---------------------------------------------------------------- writing

bool is_rotation_times_scale(const Eigen::Matrix3d& m) {
  const Eigen::Vector3d norms = m.colwise().norm();
  const Eigen::Matrix3d r = m * norms.cwiseInverse().asDiagonal();
  return (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() < 1e-5;
}

void set_qform(Nifti1Header& h, const Eigen::Matrix4d& a) {
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
  h.qform_code = kXformScannerAnat;
}

Nifti1Header make_header(const Grid3& g, std::int16_t datatype, int ncomp, std::string_view what) {
  for (int d = 0; d < 3; ++d)
    if (g.dims[d] <= 0 || g.dims[d] > 32767)
      fail(what, "cannot write dimension " + std::to_string(g.dims[d]) + " (NIfTI-1 allows 1..32767)");
  validate_world_from_voxel(g.world_from_voxel, what);
  Nifti1Header h{};
  h.sizeof_hdr = 348;
  h.regular = 'r';
  h.dim[0] = ncomp > 1 ? 5 : 3;
  for (int d = 0; d < 3; ++d) h.dim[d + 1] = static_cast<std::int16_t>(g.dims[d]);
  for (int d = 4; d < 8; ++d) h.dim[d] = 1;
  h.dim[5] = static_cast<std::int16_t>(ncomp);
  h.datatype = datatype;
  h.bitpix = static_cast<std::int16_t>(8 * bytes_per_voxel(datatype));
  const Eigen::Vector3d sp = g.spacing_mm();
  h.pixdim[0] = 1.f;
  for (int d = 0; d < 3; ++d) h.pixdim[d + 1] = static_cast<float>(sp[d]);
  for (int d = 4; d < 8; ++d) h.pixdim[d] = 1.f;
  h.vox_offset = static_cast<float>(kDataOffset);
  h.scl_slope = 1.f;
  h.xyzt_units = 2 | 8;  // mm, s
  std::memcpy(h.descrip, "brainshift", 10);
  const Eigen::Matrix4d& a = g.world_from_voxel;
  for (int c = 0; c < 4; ++c) {
    h.srow_x[c] = static_cast<float>(a(0, c));
    h.srow_y[c] = static_cast<float>(a(1, c));
    h.srow_z[c] = static_cast<float>(a(2, c));
  }
  h.sform_code = kXformScannerAnat;
  if (is_rotation_times_scale(a.topLeftCorner<3, 3>())) set_qform(h, a);
  std::memcpy(h.magic, "n+1\0", 4);
  return h;
}

std::string gzip_bytes(const std::string& raw) {
  z_stream zs{};
  // Level 1: the daemon sends fields within a latency budget; size matters less.
  if (deflateInit2(&zs, 1, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY) != Z_OK)
    throw ComputeError("zlib deflateInit2 failed");
  std::string out(deflateBound(&zs, raw.size()), '\0');
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(raw.data()));
  zs.avail_in = static_cast<uInt>(raw.size());
  zs.next_out = reinterpret_cast<Bytef*>(out.data());
  zs.avail_out = static_cast<uInt>(out.size());
  const int rc = deflate(&zs, Z_FINISH);
  out.resize(zs.total_out);
  deflateEnd(&zs);
  if (rc != Z_STREAM_END) throw ComputeError("zlib deflate failed");
  return out;
}

std::string assemble(const Nifti1Header& h, const std::string& data, bool gzip) {
  std::string raw(kDataOffset, '\0');
  std::memcpy(raw.data(), &h, kHeaderBytes);
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
std::string encode_integer(const ImageF& img, Nifti1Header& h) {
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
    Nifti1Header h = make_header(image.grid, DT_FLOAT32, 1, what);
    std::string data(image.voxels.size() * sizeof(float), '\0');
    std::memcpy(data.data(), image.voxels.data(), data.size());
    return assemble(h, data, gzip);
  }
  Nifti1Header h = make_header(image.grid, type == VoxelType::uint8 ? DT_UINT8 : DT_INT16, 1, what);
  const std::string data = type == VoxelType::uint8 ? encode_integer<std::uint8_t>(image, h)
                                                    : encode_integer<std::int16_t>(image, h);
  return assemble(h, data, gzip);
}

std::string label_bytes_named(const LabelImage& labels, bool gzip, std::string_view what) {
  check_size(labels.grid, labels.voxels.size(), what);
  const std::uint16_t mx = labels.voxels.empty() ? 0 : *std::max_element(labels.voxels.begin(), labels.voxels.end());
  if (mx > 32767) fail(what, "label " + std::to_string(mx) + " does not fit int16 (max 32767)");
  const bool small = mx <= 255;
  Nifti1Header h = make_header(labels.grid, small ? DT_UINT8 : DT_INT16, 1, what);
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
  Nifti1Header h = make_header(field.grid, DT_FLOAT32, 3, what);
  h.intent_code = kIntentDispVect;
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

constexpr std::size_t kNoLimit = std::numeric_limits<std::size_t>::max();

}  // namespace

void validate_world_from_voxel(const Eigen::Matrix4d& a, std::string_view what) {
  if (!a.allFinite()) fail(what, "world_from_voxel affine has NaN/Inf entries");
  if ((a.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).cwiseAbs().maxCoeff() > 1e-9)
    fail(what, "world_from_voxel affine's last row is not 0 0 0 1");
  const Eigen::Matrix3d m = a.topLeftCorner<3, 3>();
  const Eigen::Vector3d sp = m.colwise().norm();
  for (int d = 0; d < 3; ++d)
    if (!(sp[d] >= 0.01 && sp[d] <= 100.0))
      fail(what, "voxel size " + std::to_string(sp[d]) + " mm along axis " + std::to_string(d) +
                     " is outside [0.01, 100] mm");
  // Relative to the voxel volume, so small voxels are not mistaken for singular.
  if (std::abs(m.determinant()) < 1e-6 * sp.prod())
    fail(what, "world_from_voxel affine is singular (voxel axes are collinear)");
}

ImageF read_scalar_image(const std::filesystem::path& path) {
  const std::string name = path.string();
  return to_scalar(decode(read_file_bytes(path), name, kNoLimit), name);
}
LabelImage read_label_image(const std::filesystem::path& path) {
  const std::string name = path.string();
  return to_labels(decode(read_file_bytes(path), name, kNoLimit), name);
}
VectorImage3 read_vector_image(const std::filesystem::path& path) {
  const std::string name = path.string();
  return to_vectors(decode(read_file_bytes(path), name, kNoLimit), name);
}

ImageF scalar_image_from_bytes(std::string_view bytes, std::string_view name, std::size_t max_bytes) {
  return to_scalar(decode(bytes, name, max_bytes), name);
}
LabelImage label_image_from_bytes(std::string_view bytes, std::string_view name, std::size_t max_bytes) {
  return to_labels(decode(bytes, name, max_bytes), name);
}
VectorImage3 vector_image_from_bytes(std::string_view bytes, std::string_view name, std::size_t max_bytes) {
  return to_vectors(decode(bytes, name, max_bytes), name);
}

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
