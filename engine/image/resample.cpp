#include "image/resample.h"

namespace brainshift {
namespace {

// Calls fn(output index, source voxel coordinate) for every target voxel,
// stepping the affine incrementally along x.
template <class Fn>
void for_each_target(const Grid3& src, const Grid3& target, const Eigen::Matrix4d& src_from_target, Fn&& fn) {
  const Eigen::Matrix4d m = src.voxel_from_world() * src_from_target * target.world_from_voxel;
  const Eigen::Vector3d step = m.block<3, 1>(0, 0);
  for (int k = 0; k < target.dims[2]; ++k)
    for (int j = 0; j < target.dims[1]; ++j) {
      const Eigen::Vector3d row = (m * Eigen::Vector4d(0, j, k, 1)).head<3>();
      std::size_t out = target.index(0, j, k);
      for (int i = 0; i < target.dims[0]; ++i, ++out) fn(out, Eigen::Vector3d(row + i * step));
    }
}

}  // namespace

float sample_linear(const ImageF& image, const Eigen::Vector3d& world_mm, float outside_value) {
  return GridSampler(image.grid).linear(image.voxels, world_mm, outside_value);
}

std::uint16_t sample_nearest(const LabelImage& labels, const Eigen::Vector3d& world_mm, std::uint16_t outside_value) {
  return GridSampler(labels.grid).nearest(labels.voxels, world_mm, outside_value);
}

ImageF resample_linear(const ImageF& src, const Grid3& target, const Eigen::Matrix4d& src_from_target,
                       float outside_value) {
  ImageF out(target, outside_value);
  for_each_target(src.grid, target, src_from_target, [&](std::size_t o, const Eigen::Vector3d& p) {
    double value;
    if (trilinear_sample<TrilinearEdge::kVoxelExtent>(src.grid, src.voxels.data(), p, &value))
      out.voxels[o] = static_cast<float>(value);
  });
  return out;
}

LabelImage resample_nearest(const LabelImage& src, const Grid3& target, const Eigen::Matrix4d& src_from_target,
                            std::uint16_t outside_value) {
  LabelImage out(target, outside_value);
  for_each_target(src.grid, target, src_from_target, [&](std::size_t o, const Eigen::Vector3d& p) {
    std::size_t index;
    if (nearest_voxel(src.grid, p, &index)) out.voxels[o] = src.voxels[index];
  });
  return out;
}

}  // namespace brainshift
