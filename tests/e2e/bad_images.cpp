#include "bad_images.h"

#include <zlib.h>

#include <cstring>
#include <limits>
#include <stdexcept>

#include "image/nifti_io.h"

namespace brainshift::e2e {
namespace {

template <class T>
std::string poked(std::string bytes, std::size_t offset, T value) {
  std::memcpy(bytes.data() + offset, &value, sizeof(T));
  return bytes;
}

// NIfTI-1 header offsets (nifti1.h).
constexpr std::size_t kDim = 40, kSrowX = 280, kSrowY = 296, kData = 352;

}  // namespace

std::string gzip(const std::string& raw) {
  z_stream zs{};
  if (deflateInit2(&zs, 6, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY) != Z_OK) throw std::runtime_error("zlib");
  std::string out(deflateBound(&zs, raw.size()), '\0');
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(raw.data()));
  zs.avail_in = static_cast<uInt>(raw.size());
  zs.next_out = reinterpret_cast<Bytef*>(out.data());
  zs.avail_out = static_cast<uInt>(out.size());
  deflate(&zs, Z_FINISH);
  out.resize(zs.total_out);
  deflateEnd(&zs);
  return out;
}

std::vector<ImageCase> image_cases(const std::filesystem::path& dir) {
  const LabelImage labels = read_label_image(dir / "scan_a_labels.nii.gz");
  const ImageF t1 = read_scalar_image(dir / "scan_a_t1.nii.gz");
  const std::string raw = label_image_to_bytes(labels, false);
  const std::string gz = label_image_to_bytes(labels, true);
  const std::string t1_gz = scalar_image_to_bytes(t1, VoxelType::float32, true);
  std::vector<ImageCase> cases;
  cases.push_back({"truncated .nii.gz", gz.substr(0, gz.size() / 2), {}, "truncated", true});
  cases.push_back({"truncated .nii", raw.substr(0, raw.size() - 1000), {}, "truncated", true});
  std::string corrupt = gz;
  for (std::size_t i = gz.size() / 3; i < gz.size() / 3 + 16; ++i) corrupt[i] = static_cast<char>(~corrupt[i]);
  cases.push_back({"corrupt gzip", corrupt, {}, "gzip", true});
  cases.push_back({"not NIfTI at all", std::string(400, 'x'), {}, "NIfTI", true});
  // 2048 x 2048 x 1024 uint8 = 4 GiB claimed, 64 MiB of zeros actually sent (64 KiB gzipped).
  std::string bomb = raw.substr(0, kData);
  bomb = poked<std::int16_t>(bomb, kDim + 2, 2048);
  bomb = poked<std::int16_t>(bomb, kDim + 4, 2048);
  bomb = poked<std::int16_t>(bomb, kDim + 6, 1024);
  cases.push_back({"gzip bomb", gzip(bomb + std::string(std::size_t{64} << 20, '\0')), {}, "limit", true});
  std::string four_d = poked<std::int16_t>(raw, kDim, 4);
  four_d = poked<std::int16_t>(four_d, kDim + 8, 2);
  cases.push_back({"4-D labels", gzip(four_d + raw.substr(kData)), {}, "3-D", true});
  cases.push_back({"zero-sized", gzip(poked<std::int16_t>(raw, kDim + 4, 0)), {}, "zero-sized", true});
  cases.push_back({"absurd voxel size", gzip(poked<float>(raw, kSrowX, 5000.f)), {}, "voxel size", true});
  std::string singular = poked<float>(raw, kSrowX + 4, 1.4f);  // the j axis along the i axis: collinear
  singular = poked<float>(singular, kSrowY + 4, 0.f);
  cases.push_back({"singular affine", gzip(singular), {}, "singular", true});
  std::string nan_t1 = scalar_image_to_bytes(t1, VoxelType::float32, false);
  nan_t1 = poked<float>(nan_t1, kData + 4 * 1000, std::numeric_limits<float>::quiet_NaN());
  nan_t1 = poked<float>(nan_t1, kData + 4 * 2000, std::numeric_limits<float>::infinity());
  cases.push_back({"NaN/Inf in the image", gz, gzip(nan_t1), "NaN", true});
  ImageF shifted = t1;
  shifted.grid.world_from_voxel.col(3) += 0.5 * shifted.grid.world_from_voxel.col(0);  // half a voxel
  cases.push_back({"image grid differs from the labels'", gz, scalar_image_to_bytes(shifted, VoxelType::float32, true),
                   "grid differs", true});
  LabelImage unknown = labels;
  for (std::size_t i = 0; i < unknown.voxels.size(); i += 97)
    if (unknown.voxels[i] == 1) unknown.voxels[i] = 7;
  cases.push_back({"labels not in the table", label_image_to_bytes(unknown, true), t1_gz, "not in the label table", false});
  LabelImage no_brain = labels;
  for (auto& v : no_brain.voxels)
    if (v == 1) v = 0;
  cases.push_back({"empty brain label", label_image_to_bytes(no_brain, true), t1_gz, "brain label", false});
  LabelImage partial = labels;  // a slab of 12 of the 44 slices
  for (int k = 12; k < partial.grid.dims[2]; ++k)
    for (int j = 0; j < partial.grid.dims[1]; ++j)
      for (int i = 0; i < partial.grid.dims[0]; ++i) partial.at(i, j, k) = 0;
  cases.push_back({"field of view misses most of the brain", label_image_to_bytes(partial, true), t1_gz,
                   "field of view", false});
  return cases;
}

}  // namespace brainshift::e2e
