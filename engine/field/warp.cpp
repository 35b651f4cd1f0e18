#include "field/warp.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "core/errors.h"

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
// evaluated without per-voxel matrix inversions.
template <class Sink>
void for_each_pullback(const Grid3& preop, const VectorImage3& pullback, Sink&& sink) {
  const Eigen::Matrix4d m = preop.voxel_from_world() * pullback.grid.world_from_voxel;
  const Eigen::Matrix3d lin = m.topLeftCorner<3, 3>();
  const Eigen::Vector3d off = m.topRightCorner<3, 1>();
  const Eigen::Matrix3d to_voxel = preop.voxel_from_world().topLeftCorner<3, 3>();
  const Grid3& g = pullback.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j) {
      Eigen::Vector3d base = lin * Eigen::Vector3d(0, j, k) + off;
      std::size_t v = g.index(0, j, k);
      for (int i = 0; i < g.dims[0]; ++i, ++v) {
        const Eigen::Vector3d c = base + lin.col(0) * i + to_voxel * pullback.vectors[v].cast<double>();
        sink(v, c);
      }
    }
}

bool inside(const Eigen::Vector3d& c, const std::array<int, 3>& dims) {
  return c.x() >= -0.5 && c.y() >= -0.5 && c.z() >= -0.5 && c.x() <= dims[0] - 0.5 &&
         c.y() <= dims[1] - 0.5 && c.z() <= dims[2] - 0.5;
}

float trilinear(const ImageF& image, const Eigen::Vector3d& c) {
  const auto& d = image.grid.dims;
  int lo[3], hi[3];
  float t[3];
  for (int a = 0; a < 3; ++a) {
    const double x = std::clamp(c[a], 0.0, static_cast<double>(d[a] - 1));
    lo[a] = std::min(static_cast<int>(x), d[a] - 1);
    hi[a] = std::min(lo[a] + 1, d[a] - 1);
    t[a] = static_cast<float>(x - lo[a]);
  }
  const auto at = [&](int i, int j, int k) { return image.voxels[image.grid.index(i, j, k)]; };
  const float c00 = at(lo[0], lo[1], lo[2]) + t[0] * (at(hi[0], lo[1], lo[2]) - at(lo[0], lo[1], lo[2]));
  const float c10 = at(lo[0], hi[1], lo[2]) + t[0] * (at(hi[0], hi[1], lo[2]) - at(lo[0], hi[1], lo[2]));
  const float c01 = at(lo[0], lo[1], hi[2]) + t[0] * (at(hi[0], lo[1], hi[2]) - at(lo[0], lo[1], hi[2]));
  const float c11 = at(lo[0], hi[1], hi[2]) + t[0] * (at(hi[0], hi[1], hi[2]) - at(lo[0], hi[1], hi[2]));
  const float c0 = c00 + t[1] * (c10 - c00);
  const float c1 = c01 + t[1] * (c11 - c01);
  return c0 + t[2] * (c1 - c0);
}

}  // namespace

ImageF warp_image_linear(const ImageF& preop, const VectorImage3& pullback, float outside_value) {
  check(preop.grid, pullback);
  ImageF out(pullback.grid, outside_value);
  for_each_pullback(preop.grid, pullback, [&](std::size_t v, const Eigen::Vector3d& c) {
    if (inside(c, preop.grid.dims)) out.voxels[v] = trilinear(preop, c);
  });
  return out;
}

LabelImage warp_labels_nearest(const LabelImage& preop, const VectorImage3& pullback,
                               std::uint16_t outside_value) {
  check(preop.grid, pullback);
  LabelImage out(pullback.grid, outside_value);
  const auto& d = preop.grid.dims;
  for_each_pullback(preop.grid, pullback, [&](std::size_t v, const Eigen::Vector3d& c) {
    if (!inside(c, d)) return;
    // Round half up; clamp keeps the outer half voxel on the edge voxel.
    const int i = std::clamp(static_cast<int>(std::floor(c.x() + 0.5)), 0, d[0] - 1);
    const int j = std::clamp(static_cast<int>(std::floor(c.y() + 0.5)), 0, d[1] - 1);
    const int k = std::clamp(static_cast<int>(std::floor(c.z() + 0.5)), 0, d[2] - 1);
    out.voxels[v] = preop.at(i, j, k);
  });
  return out;
}

}  // namespace brainshift
