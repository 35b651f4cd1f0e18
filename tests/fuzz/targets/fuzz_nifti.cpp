// libFuzzer target: the NIfTI-1/NIfTI-2 reader on in-memory bytes (raw or gzip), as
// brainshiftd uses it for pushed scans and uploaded preops.
//
// Oracles, besides ASan/UBSan/LeakSanitizer:
// - the only exception the reader may throw is InputError (the daemon maps it
//   to invalid_request; anything else would be "internal" or a crash);
// - memory stays bounded by the decompressed-size limit (run_fuzzers.sh sets
//   -malloc_limit_mb to 8x kMaxBytes: a larger allocation is a finding);
// - what reads back is a consistent image that survives write + read unchanged.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string_view>

#include "core/errors.h"
#include "image/nifti_io.h"

namespace {

using namespace brainshift;

// The reader's bound on decompressed bytes in this target (the daemon's is
// engine_.max_image_bytes(), far larger; the logic is the same).
constexpr std::size_t kMaxBytes = std::size_t{32} << 20;

[[noreturn]] void violated(const char* what) {
  std::fprintf(stderr, "fuzz_nifti: property violated: %s\n", what);
  std::abort();
}

void require(bool ok, const char* what) {
  if (!ok) violated(what);
}

void check_grid(const Grid3& g, std::size_t values) {
  require(g.dims[0] > 0 && g.dims[1] > 0 && g.dims[2] > 0, "positive dims");
  require(g.voxel_count() == values, "voxel buffer matches the grid");
  require(g.world_from_voxel.allFinite(), "finite affine");
}

// Geometry read from a qform is computed in double and written back as a float
// sform, so a round trip may move it by float rounding, never more.
bool same_geometry(const Grid3& a, const Grid3& b) {
  const double scale = 1.0 + a.world_from_voxel.cwiseAbs().maxCoeff();
  return a.dims == b.dims && (a.world_from_voxel - b.world_from_voxel).cwiseAbs().maxCoeff() <= 1e-5 * scale;
}

void read_labels(std::string_view bytes) {
  try {
    const LabelImage labels = label_image_from_bytes(bytes, "labels", kMaxBytes);
    check_grid(labels.grid, labels.voxels.size());
    std::string written;
    try {
      written = label_image_to_bytes(labels, /*gzip=*/false);
    } catch (const InputError&) {
      return;  // labels above 32767 cannot be written as int16: a documented refusal
    }
    const LabelImage back = label_image_from_bytes(written, "labels again", kMaxBytes);
    require(same_geometry(back.grid, labels.grid) && back.voxels == labels.voxels, "label round trip");
  } catch (const InputError&) {
  }
}

void read_scalar(std::string_view bytes) {
  try {
    const ImageF image = scalar_image_from_bytes(bytes, "image", kMaxBytes);
    check_grid(image.grid, image.voxels.size());
    for (float v : image.voxels) require(std::isfinite(v), "finite voxels");
    const ImageF back = scalar_image_from_bytes(scalar_image_to_bytes(image, VoxelType::float32, true), "again",
                                                kMaxBytes);
    require(same_geometry(back.grid, image.grid) && back.voxels == image.voxels, "scalar round trip");
  } catch (const InputError&) {
  }
}

void read_vectors(std::string_view bytes) {
  try {
    const VectorImage3 field = vector_image_from_bytes(bytes, "field", kMaxBytes);
    check_grid(field.grid, field.vectors.size());
    const VectorImage3 back =
        vector_image_from_bytes(displacement_field_to_bytes(field, false), "again", kMaxBytes);
    require(same_geometry(back.grid, field.grid) && back.vectors == field.vectors, "field round trip");
  } catch (const InputError&) {
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  read_labels(bytes);
  read_scalar(bytes);
  read_vectors(bytes);
  return 0;
}
