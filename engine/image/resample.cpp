#include "image/resample.h"

#include <algorithm>
#include <cmath>

namespace brainshift {
namespace {

bool inside_extent(const Eigen::Vector3d& p, const std::array<int, 3>& dims) {
  for (int d = 0; d < 3; ++d)
    if (!(p[d] >= -0.5 && p[d] <= dims[d] - 0.5)) return false;  // also rejects NaN
  return true;
}

// p in continuous voxel coordinates, already known to be inside the extent.
float trilinear(const ImageF& img, const Eigen::Vector3d& p) {
  const auto& dims = img.grid.dims;
  int i0[3], i1[3];
  double f[3];
  for (int d = 0; d < 3; ++d) {
    const double c = std::clamp(p[d], 0.0, static_cast<double>(dims[d] - 1));
    i0[d] = std::min(static_cast<int>(c), dims[d] - 1);
    i1[d] = std::min(i0[d] + 1, dims[d] - 1);
    f[d] = c - i0[d];
  }
  const float* v = img.voxels.data();
  const auto& g = img.grid;
  auto at = [&](int i, int j, int k) { return static_cast<double>(v[g.index(i, j, k)]); };
  const double c00 = at(i0[0], i0[1], i0[2]) * (1 - f[0]) + at(i1[0], i0[1], i0[2]) * f[0];
  const double c10 = at(i0[0], i1[1], i0[2]) * (1 - f[0]) + at(i1[0], i1[1], i0[2]) * f[0];
  const double c01 = at(i0[0], i0[1], i1[2]) * (1 - f[0]) + at(i1[0], i0[1], i1[2]) * f[0];
  const double c11 = at(i0[0], i1[1], i1[2]) * (1 - f[0]) + at(i1[0], i1[1], i1[2]) * f[0];
  const double c0 = c00 * (1 - f[1]) + c10 * f[1];
  const double c1 = c01 * (1 - f[1]) + c11 * f[1];
  return static_cast<float>(c0 * (1 - f[2]) + c1 * f[2]);
}

std::uint16_t nearest(const LabelImage& img, const Eigen::Vector3d& p) {
  const auto& dims = img.grid.dims;
  int idx[3];
  for (int d = 0; d < 3; ++d)
    idx[d] = std::clamp(static_cast<int>(std::floor(p[d] + 0.5)), 0, dims[d] - 1);
  return img.voxels[img.grid.index(idx[0], idx[1], idx[2])];
}

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
  const Eigen::Vector3d p = (image.grid.voxel_from_world() * world_mm.homogeneous()).head<3>();
  return inside_extent(p, image.grid.dims) ? trilinear(image, p) : outside_value;
}

std::uint16_t sample_nearest(const LabelImage& labels, const Eigen::Vector3d& world_mm, std::uint16_t outside_value) {
  const Eigen::Vector3d p = (labels.grid.voxel_from_world() * world_mm.homogeneous()).head<3>();
  return inside_extent(p, labels.grid.dims) ? nearest(labels, p) : outside_value;
}

ImageF resample_linear(const ImageF& src, const Grid3& target, const Eigen::Matrix4d& src_from_target,
                       float outside_value) {
  ImageF out(target, outside_value);
  for_each_target(src.grid, target, src_from_target, [&](std::size_t o, const Eigen::Vector3d& p) {
    if (inside_extent(p, src.grid.dims)) out.voxels[o] = trilinear(src, p);
  });
  return out;
}

LabelImage resample_nearest(const LabelImage& src, const Grid3& target, const Eigen::Matrix4d& src_from_target,
                            std::uint16_t outside_value) {
  LabelImage out(target, outside_value);
  for_each_target(src.grid, target, src_from_target, [&](std::size_t o, const Eigen::Vector3d& p) {
    if (inside_extent(p, src.grid.dims)) out.voxels[o] = nearest(src, p);
  });
  return out;
}

}  // namespace brainshift
