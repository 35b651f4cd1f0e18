#include "synthetic_head.h"

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "image/resample.h"

namespace brainshift::test {
namespace {

double ellipsoid(const Eigen::Vector3d& p, const Eigen::Vector3d& c, const Eigen::Vector3d& r) {
  return (p - c).cwiseQuotient(r).squaredNorm();
}

}  // namespace

SyntheticHead synthetic_head(const SyntheticHeadSpec& spec) {
  Grid3 g;
  g.dims = spec.dims;
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  g.world_from_voxel.topLeftCorner<3, 3>() *= spec.spacing_mm;
  g.world_from_voxel.block<3, 1>(0, 3) = spec.origin_mm;
  SyntheticHead h{ImageF(g), LabelImage(g)};
  const Eigen::Vector3d& v = spec.ventricle_semi_axes_mm;
  const Eigen::Vector3d tumor = Eigen::Vector3d::Constant(spec.tumor_radius_mm);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d p = g.world_mm(i, j, k);
        std::uint16_t l = 0;
        if (ellipsoid(p, {0, 0, 0}, {55, 65, 48}) < 1) l = 1;
        if (ellipsoid(p, {-12, 5, 8}, v) < 1 || ellipsoid(p, {12, 5, 8}, v) < 1) l = 2;
        if (ellipsoid(p, {25, -20, -10}, tumor) < 1) l = 4;
        h.labels.at(i, j, k) = l;
        h.t1.at(i, j, k) = l == 0 ? 10.f : l == 2 ? 30.f : l == 4 ? 150.f : 100.f;
      }
  return h;
}

ImageF scanner_image(const ImageF& clean) {
  ImageF out = clean;
  std::uint32_t state = 12345;
  auto uniform = [&] {
    state = state * 1664525u + 1013904223u;
    return (state >> 8) / 16777216.0;
  };
  for (int k = 0; k < out.grid.dims[2]; ++k)
    for (int j = 0; j < out.grid.dims[1]; ++j)
      for (int i = 0; i < out.grid.dims[0]; ++i) {
        const double b = 1.0 + 0.15 * (i / double(out.grid.dims[0]) - 0.5) + 0.1 * (k / double(out.grid.dims[2]) - 0.5);
        const double n = 3.0 * std::sqrt(-2 * std::log(uniform() + 1e-12)) * std::cos(6.283185307 * uniform());
        out.at(i, j, k) = static_cast<float>(std::max(0.0, b * out.at(i, j, k) + n));
      }
  return out;
}

double outline_dice(const LabelImage& a, const LabelImage& b) {
  std::size_t both = 0, na = 0, nb = 0;
  for (std::size_t v = 0; v < a.voxels.size(); ++v) {
    both += a.voxels[v] && b.voxels[v];
    na += a.voxels[v] != 0;
    nb += b.voxels[v] != 0;
  }
  return 2.0 * static_cast<double>(both) / static_cast<double>(na + nb);
}

MovedHead move_head(const LabelImage& labels, const ImageF& t1, const Grid3& grid, const Eigen::Vector3d& shift_mm) {
  Eigen::Matrix4d preop_from_intraop = Eigen::Matrix4d::Identity();
  preop_from_intraop.block<3, 1>(0, 3) = -shift_mm;
  MovedHead moved{resample_nearest(labels, grid, preop_from_intraop), resample_linear(t1, grid, preop_from_intraop)};
  for (auto& v : moved.labels.voxels)
    if (v == 4) v = 1;
  return moved;
}

void sink_top(LabelImage& labels, double depth_mm, double radius_mm) {
  const Grid3& g = labels.grid;
  double top = -1e9;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        if (labels.at(i, j, k)) top = std::max(top, g.world_mm(i, j, k).z());
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d p = g.world_mm(i, j, k);
        if (p.z() > top - depth_mm && p.head<2>().norm() < radius_mm) labels.at(i, j, k) = 0;
      }
}

}  // namespace brainshift::test
