#pragma once
// Synthetic label images with known geometry for the meshing tests.
#include <cmath>

#include "core/image.h"

namespace brainshift::test {

// Ellipsoid test in voxel-centre coordinates relative to `centre` (voxels).
inline bool inside_ellipsoid(double i, double j, double k, const Eigen::Vector3d& centre, const Eigen::Vector3d& semi) {
  const Eigen::Vector3d d = (Eigen::Vector3d(i, j, k) - centre).cwiseQuotient(semi);
  return d.squaredNorm() <= 1.0;
}

struct Region {
  Eigen::Vector3d centre, semi_axes;  // voxels
  std::uint16_t label;
};

// Paints `regions` in order (later ones overwrite earlier ones) on an empty grid.
inline LabelImage paint(const Grid3& grid, const std::vector<Region>& regions) {
  LabelImage img(grid, 0);
  for (int k = 0; k < grid.dims[2]; ++k)
    for (int j = 0; j < grid.dims[1]; ++j)
      for (int i = 0; i < grid.dims[0]; ++i)
        for (const auto& r : regions)
          if (inside_ellipsoid(i, j, k, r.centre, r.semi_axes)) img.at(i, j, k) = r.label;
  return img;
}

inline std::size_t count_voxels(const LabelImage& img, std::uint16_t label) {
  std::size_t n = 0;
  for (auto v : img.voxels) n += (v == label);
  return n;
}

inline double voxel_volume_mm3(const Grid3& g) {
  return std::abs(g.world_from_voxel.topLeftCorner<3, 3>().determinant());
}

}  // namespace brainshift::test
