#pragma once
// Synthetic inputs for the registration tests: transforms, grids, label maps
// and an icosphere surface. Everything is analytic so the truth is known.
#include <Eigen/Geometry>
#include <cmath>
#include <functional>
#include <map>
#include <utility>

#include "core/image.h"
#include "core/tet_mesh.h"

namespace brainshift::test {

inline Eigen::Matrix4d make_affine(const Eigen::Vector3d& rot_deg, const Eigen::Vector3d& scale,
                                   double shear_xy, const Eigen::Vector3d& translation_mm,
                                   const Eigen::Vector3d& centre_mm) {
  const double d2r = M_PI / 180.0;
  const Eigen::Matrix3d R = (Eigen::AngleAxisd(rot_deg.z() * d2r, Eigen::Vector3d::UnitZ()) *
                             Eigen::AngleAxisd(rot_deg.y() * d2r, Eigen::Vector3d::UnitY()) *
                             Eigen::AngleAxisd(rot_deg.x() * d2r, Eigen::Vector3d::UnitX()))
                                .toRotationMatrix();
  Eigen::Matrix3d S = scale.asDiagonal();
  S(0, 1) = shear_xy;
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topLeftCorner<3, 3>() = R * S;
  // About centre_mm, so "translation" is the motion of the brain centre.
  m.topRightCorner<3, 1>() = centre_mm + translation_mm - R * S * centre_mm;
  return m;
}

// Grid with the given spacing and an orientation, centred on centre_mm.
inline Grid3 make_grid(std::array<int, 3> dims, const Eigen::Vector3d& spacing_mm,
                       const Eigen::Matrix3d& rotation, const Eigen::Vector3d& centre_mm) {
  Grid3 g;
  g.dims = dims;
  g.world_from_voxel.topLeftCorner<3, 3>() = rotation * spacing_mm.asDiagonal();
  const Eigen::Vector3d half((dims[0] - 1) / 2.0, (dims[1] - 1) / 2.0, (dims[2] - 1) / 2.0);
  g.world_from_voxel.topRightCorner<3, 1>() = centre_mm - rotation * spacing_mm.cwiseProduct(half);
  return g;
}

inline LabelImage rasterise(const Grid3& grid,
                            const std::function<std::uint16_t(const Eigen::Vector3d&)>& label_at) {
  LabelImage img(grid, 0);
  for (int k = 0; k < grid.dims[2]; ++k)
    for (int j = 0; j < grid.dims[1]; ++j)
      for (int i = 0; i < grid.dims[0]; ++i) img.at(i, j, k) = label_at(grid.world_mm(i, j, k));
  return img;
}

// Maximum |A p - B p| over the voxel centres of a label map (all non-zero voxels).
inline double max_displacement_difference_mm(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b,
                                             const LabelImage& labels) {
  double m = 0;
  const Eigen::Matrix4d d = a - b;
  for (int k = 0; k < labels.grid.dims[2]; ++k)
    for (int j = 0; j < labels.grid.dims[1]; ++j)
      for (int i = 0; i < labels.grid.dims[0]; ++i)
        if (labels.at(i, j, k))
          m = std::max(m, (d * labels.grid.world_mm(i, j, k).homogeneous()).head<3>().norm());
  return m;
}

// Angle (deg) between the rotation parts (polar decomposition) of two affines.
inline double rotation_difference_deg(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b) {
  auto rot = [](const Eigen::Matrix4d& m) {
    Eigen::JacobiSVD<Eigen::Matrix3d> svd(m.topLeftCorner<3, 3>(), Eigen::ComputeFullU | Eigen::ComputeFullV);
    return Eigen::Matrix3d(svd.matrixU() * svd.matrixV().transpose());
  };
  return Eigen::AngleAxisd(rot(a).transpose() * rot(b)).angle() * 180.0 / M_PI;
}

// Icosphere: subdivided icosahedron projected on a sphere, outward triangles.
inline TriSurface icosphere(const Eigen::Vector3d& centre, double radius, int subdivisions) {
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<Eigen::Vector3d> v{{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0},
                                 {0, -1, t}, {0, 1, t}, {0, -1, -t}, {0, 1, -t},
                                 {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
  std::vector<std::array<int, 3>> f{{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                                    {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                                    {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                                    {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};
  for (auto& p : v) p.normalize();
  for (int s = 0; s < subdivisions; ++s) {
    std::map<std::pair<int, int>, int> mid;
    auto midpoint = [&](int a, int b) {
      const auto key = std::minmax(a, b);
      auto it = mid.find(key);
      if (it != mid.end()) return it->second;
      v.push_back((v[a] + v[b]).normalized());
      mid[key] = static_cast<int>(v.size()) - 1;
      return static_cast<int>(v.size()) - 1;
    };
    std::vector<std::array<int, 3>> nf;
    for (const auto& tri : f) {
      const int a = midpoint(tri[0], tri[1]), b = midpoint(tri[1], tri[2]), c = midpoint(tri[2], tri[0]);
      nf.push_back({tri[0], a, c});
      nf.push_back({tri[1], b, a});
      nf.push_back({tri[2], c, b});
      nf.push_back({a, b, c});
    }
    f.swap(nf);
  }
  TriSurface s;
  for (const auto& p : v) s.vertices_mm.push_back(centre + radius * p);
  s.triangles = f;
  return s;
}

}  // namespace brainshift::test
