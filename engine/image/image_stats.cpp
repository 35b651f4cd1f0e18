#include "image/image_stats.h"

#include <algorithm>
#include <cmath>
#include <iterator>

#include "core/errors.h"

namespace brainshift {

VoxelBox bounding_box_voxels(const Mask& mask) {
  VoxelBox box;
  const auto& g = mask.grid;
  box.lo = {g.dims[0], g.dims[1], g.dims[2]};
  // Row by row: the first and the last voxel set in a row bound it along x
  // (the masks of a scan are a few per cent of a 4-million-voxel grid).
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j) {
      const auto row = mask.voxels.begin() + static_cast<std::ptrdiff_t>(g.index(0, j, k));
      const auto end = row + g.dims[0];
      const auto first = std::find_if(row, end, [](std::uint8_t v) { return v != 0; });
      if (first == end) continue;
      const auto last = std::find_if(std::make_reverse_iterator(end), std::make_reverse_iterator(first),
                                     [](std::uint8_t v) { return v != 0; });
      const int i0 = static_cast<int>(first - row), i1 = static_cast<int>(last.base() - row) - 1;
      box.lo = {std::min(box.lo[0], i0), std::min(box.lo[1], j), std::min(box.lo[2], k)};
      box.hi = {std::max(box.hi[0], i1), std::max(box.hi[1], j), std::max(box.hi[2], k)};
      box.empty = false;
    }
  if (box.empty) box = VoxelBox{};
  return box;
}

VoxelBox grow_box(const VoxelBox& box, const Grid3& grid, double margin_mm) {
  if (box.empty) return box;
  VoxelBox out = box;
  const Eigen::Vector3d spacing = grid.spacing_mm();
  for (int a = 0; a < 3; ++a) {
    const int m = static_cast<int>(std::ceil(margin_mm / spacing[a]));
    out.lo[a] = std::max(0, box.lo[a] - m);
    out.hi[a] = std::min(grid.dims[a] - 1, box.hi[a] + m);
  }
  return out;
}

Mask crop_to_box(const Mask& mask, const VoxelBox& box) {
  if (box.empty) throw InputError("crop_to_box: empty box");
  Grid3 g;
  for (int a = 0; a < 3; ++a) g.dims[a] = box.hi[a] - box.lo[a] + 1;
  g.world_from_voxel = mask.grid.world_from_voxel;
  g.world_from_voxel.block<3, 1>(0, 3) = mask.grid.world_mm(box.lo[0], box.lo[1], box.lo[2]);
  Mask out(g, 0);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j) {
      const std::uint8_t* src = &mask.voxels[mask.grid.index(box.lo[0], j + box.lo[1], k + box.lo[2])];
      std::copy(src, src + g.dims[0], &out.voxels[g.index(0, j, k)]);
    }
  return out;
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

float median_in_place(std::vector<float>& values) {
  if (values.empty()) return 0.f;
  const auto mid = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
  std::nth_element(values.begin(), mid, values.end());
  return *mid;
}

}  // namespace brainshift
