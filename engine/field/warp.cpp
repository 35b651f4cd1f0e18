#include "field/warp.h"

#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "image/interpolation.h"

namespace brainshift {
namespace {

void check(const Grid3& preop, const VectorImage3& pullback) {
  if (pullback.vectors.size() != pullback.grid.voxel_count()) {
    throw InputError("warp: the pull-back field has " + std::to_string(pullback.vectors.size()) +
                     " vectors for a grid of " + std::to_string(pullback.grid.voxel_count()) + " voxels");
  }
  if (preop.voxel_count() == 0) throw InputError("warp: the preop image is empty");
}

// Calls sink(v, preop_voxel_coordinate) for every output voxel v. The map from
// output voxel to preop voxel coordinates is affine plus the field, so it is
// evaluated without per-voxel matrix inversions. Each output voxel on its
// own: the slices in two halves side by side (core/parallel.h).
template <class Sink>
void for_each_pullback(const Grid3& preop, const VectorImage3& pullback, Sink&& sink) {
  const Eigen::Matrix4d m = preop.voxel_from_world() * pullback.grid.world_from_voxel;
  const Eigen::Matrix3d lin = m.topLeftCorner<3, 3>();
  const Eigen::Vector3d off = m.topRightCorner<3, 1>();
  const Eigen::Matrix3d to_voxel = preop.voxel_from_world().topLeftCorner<3, 3>();
  const Grid3& g = pullback.grid;
  parallel_halves(static_cast<std::size_t>(g.dims[2]), 4, [&](std::size_t k0, std::size_t k1) {
    for (auto k = static_cast<int>(k0); k < static_cast<int>(k1); ++k)
      for (int j = 0; j < g.dims[1]; ++j) {
        const Eigen::Vector3d base = lin * Eigen::Vector3d(0, j, k) + off;
        std::size_t v = g.index(0, j, k);
        for (int i = 0; i < g.dims[0]; ++i, ++v) {
          const Eigen::Vector3d c = base + lin.col(0) * i + to_voxel * pullback.vectors[v].cast<double>();
          sink(v, c);
        }
      }
  });
}

}  // namespace

ImageF warp_image_linear(const ImageF& preop, const VectorImage3& pullback, float outside_value) {
  check(preop.grid, pullback);
  ImageF out(pullback.grid, outside_value);
  // Float arithmetic: this runs for every voxel of the scan.
  for_each_pullback(preop.grid, pullback, [&](std::size_t v, const Eigen::Vector3d& c) {
    trilinear_sample<TrilinearEdge::kVoxelExtent, float>(preop.grid, preop.voxels.data(), c, &out.voxels[v]);
  });
  return out;
}

LabelImage warp_labels_nearest(const LabelImage& preop, const VectorImage3& pullback,
                               std::uint16_t outside_value) {
  check(preop.grid, pullback);
  LabelImage out(pullback.grid, outside_value);
  for_each_pullback(preop.grid, pullback, [&](std::size_t v, const Eigen::Vector3d& c) {
    std::size_t index;
    if (nearest_voxel(preop.grid, c, &index)) out.voxels[v] = preop.voxels[index];
  });
  return out;
}

}  // namespace brainshift
