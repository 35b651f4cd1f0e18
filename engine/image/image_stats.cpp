#include "image/image_stats.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"

namespace brainshift {

VoxelBox bounding_box_voxels(const Mask& mask) {
  VoxelBox box;
  const auto& g = mask.grid;
  box.lo = {g.dims[0], g.dims[1], g.dims[2]};
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        if (!mask.voxels[g.index(i, j, k)]) continue;
        const int p[3] = {i, j, k};
        for (int d = 0; d < 3; ++d) {
          box.lo[d] = std::min(box.lo[d], p[d]);
          box.hi[d] = std::max(box.hi[d], p[d]);
        }
        box.empty = false;
      }
  if (box.empty) box = VoxelBox{};
  return box;
}

std::size_t count_nonzero(const Mask& mask) {
  return static_cast<std::size_t>(std::count_if(mask.voxels.begin(), mask.voxels.end(), [](std::uint8_t v) { return v != 0; }));
}

double volume_ml(const Mask& mask) {
  const double voxel_mm3 = std::abs(mask.grid.world_from_voxel.topLeftCorner<3, 3>().determinant());
  return static_cast<double>(count_nonzero(mask)) * voxel_mm3 / 1000.0;
}

Eigen::Vector3d centroid_mm(const Mask& mask) {
  const auto& g = mask.grid;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  std::size_t n = 0;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        if (mask.voxels[g.index(i, j, k)]) {
          sum += Eigen::Vector3d(i, j, k);
          ++n;
        }
  if (n == 0) throw InputError("centroid_mm: the mask is empty");
  // The affine is linear, so the centroid of the voxel indices maps exactly.
  return g.world_mm(sum[0] / n, sum[1] / n, sum[2] / n);
}

}  // namespace brainshift
