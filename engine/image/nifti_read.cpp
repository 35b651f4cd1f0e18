// NIfTI-1 and NIfTI-2 readers, from files and from in-memory bytes. The
// header is decoded first and the decompressed size it claims is checked
// against the caller's bound before any voxel buffer is allocated; the buffer
// then grows only as data actually arrive.
#include <nifti/nifti1.h>

#include <algorithm>
#include <array>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

#include "core/errors.h"
#include "core/file_bytes.h"
#include "image/nifti_gzip.h"
#include "image/nifti_header.h"
#include "image/nifti_io.h"

namespace brainshift {
namespace {

using nifti_detail::ByteStream;
using nifti_detail::NiftiHeader;

[[noreturn]] void fail(std::string_view name, const std::string& what) {
  throw InputError(std::string(name) + ": " + what);
}

struct RawNifti {
  NiftiHeader hdr;
  std::array<std::int64_t, 7> dims{1, 1, 1, 1, 1, 1, 1};
  std::size_t voxel_count = 0;  // product of all dims
  std::string data;             // exactly voxel_count * bytes_per_voxel bytes
};

// dims from dim[0..7]; the product of all seven is guarded in long double by
// the caller (seven dims of 32767, or NIfTI-2's int64 dims, overflow 64 bits).
void read_dims(RawNifti& raw, std::string_view name) {
  const NiftiHeader& h = raw.hdr;
  if (h.dim[0] < 1 || h.dim[0] > 7) fail(name, "invalid dim[0] = " + std::to_string(h.dim[0]));
  for (int d = 1; d <= h.dim[0]; ++d) {
    if (h.dim[d] <= 0)
      fail(name, "zero-sized or negative dimension dim[" + std::to_string(d) + "] = " + std::to_string(h.dim[d]));
    raw.dims[d - 1] = h.dim[d];
  }
  // Grid3 counts voxels along an axis in int; a NIfTI-2 int64 beyond that is refused.
  for (int d = 0; d < 3; ++d)
    if (raw.dims[d] > INT_MAX)
      fail(name, "dimension dim[" + std::to_string(d + 1) + "] = " + std::to_string(raw.dims[d]) +
                     " is larger than this reader supports (" + std::to_string(INT_MAX) + ")");
}

// vox_offset is where the data start: at least the header size, at most 1e9
// (it comes from the file; data that far away is not an image we serve).
std::size_t data_offset(const NiftiHeader& h, std::string_view name) {
  if (!(h.vox_offset >= static_cast<double>(h.header_bytes)) || h.vox_offset > 1e9)
    fail(name, "invalid vox_offset " + std::to_string(h.vox_offset) + " (NIfTI-" + std::to_string(h.version) +
                   " data start at byte " + std::to_string(h.header_bytes) + " or later)");
  return static_cast<std::size_t>(h.vox_offset);
}

// Skipped in small pieces: a tiny file claiming a huge vox_offset must not
// make us allocate the claim.
void skip_to_data(ByteStream& stream, std::size_t offset, std::size_t header_bytes, std::string_view name) {
  std::string skip(std::min<std::size_t>(offset - header_bytes, 64 * 1024), '\0');
  for (std::size_t left = offset - header_bytes; left > 0;) {
    const std::size_t n = std::min(left, skip.size());
    if (stream.read(skip.data(), n) < n)
      fail(name, "truncated: file ends before the voxel data (vox_offset " + std::to_string(offset) + ")");
    left -= n;
  }
}

// Grows the buffer as data actually arrive, so that a file whose header claims
// far more than it holds fails as truncated instead of allocating the claim.
void read_voxels(ByteStream& stream, std::size_t want, std::string& data, std::string_view name) {
  std::size_t got = 0;
  while (got < want) {
    const std::size_t next = std::min(want, std::max<std::size_t>(std::size_t{64} << 20, 2 * got));
    data.resize(next);
    const std::size_t n = stream.read(data.data() + got, next - got);
    got += n;
    if (got < next) break;
  }
  if (got < want)
    fail(name, "truncated: header promises " + std::to_string(want) + " bytes of voxel data, found only " +
                   std::to_string(got));
}

RawNifti decode(std::string_view bytes, std::string_view name, std::size_t max_bytes) {
  ByteStream stream(bytes, name);
  RawNifti raw;
  raw.hdr = nifti_detail::read_header(stream, name);
  read_dims(raw, name);
  const std::size_t bpv = nifti_detail::bytes_per_voxel(raw.hdr.datatype);
  if (bpv == 0) fail(name, "unsupported NIfTI datatype " + std::to_string(raw.hdr.datatype));
  const std::size_t offset = data_offset(raw.hdr, name);
  long double voxels = 1;
  for (int d = 0; d < 7; ++d) voxels *= static_cast<long double>(raw.dims[d]);
  const long double total = static_cast<long double>(offset) + voxels * bpv;
  if (total > static_cast<long double>(max_bytes))
    fail(name, "header claims " + std::to_string(static_cast<double>(total)) +
                   " decompressed bytes, more than the limit of " + std::to_string(max_bytes));
  raw.voxel_count = static_cast<std::size_t>(voxels);
  skip_to_data(stream, offset, raw.hdr.header_bytes, name);
  read_voxels(stream, raw.voxel_count * bpv, raw.data, name);
  if (stream.is_gzip()) stream.verify_to_end(max_bytes - static_cast<std::size_t>(total));
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
        if (raw.hdr.swapped) nifti_detail::swap_in_place(v);
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

Grid3 grid_of(const RawNifti& raw, std::string_view name) {
  Grid3 g;
  for (int d = 0; d < 3; ++d) g.dims[d] = static_cast<int>(raw.dims[d]);
  g.world_from_voxel = nifti_detail::world_from_voxel_of(raw.hdr, name);
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
  // Not a structured binding: clang 14 (the fuzz build) cannot capture one in a lambda.
  const std::pair<double, double> scale = scaling(raw, name);
  const double slope = scale.first, inter = scale.second;
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
  const std::pair<double, double> scale = scaling(raw, name);
  const double slope = scale.first, inter = scale.second;
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
  const std::pair<double, double> scale = scaling(raw, name);
  const double slope = scale.first, inter = scale.second;
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

constexpr std::size_t kNoLimit = std::numeric_limits<std::size_t>::max();

}  // namespace

ImageF read_scalar_image(const std::filesystem::path& path, std::size_t max_bytes) {
  const std::string name = path.string();
  return to_scalar(decode(read_whole_file(path, "NIfTI file"), name, max_bytes), name);
}
LabelImage read_label_image(const std::filesystem::path& path, std::size_t max_bytes) {
  const std::string name = path.string();
  return to_labels(decode(read_whole_file(path, "NIfTI file"), name, max_bytes), name);
}
VectorImage3 read_vector_image(const std::filesystem::path& path) {
  const std::string name = path.string();
  return to_vectors(decode(read_whole_file(path, "NIfTI file"), name, kNoLimit), name);
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

}  // namespace brainshift
