#pragma once
// Hand-built test meshes (no CGAL): a structured box of cubes, each split into
// the 6 Kuhn tetrahedra around its main diagonal, so neighbouring cubes share
// faces conformingly.
#include <Eigen/Dense>
#include <array>
#include <functional>

#include "core/image.h"
#include "core/tet_mesh.h"

namespace brainshift::test {

// Box with n[a] cubes of size h_mm along each axis, min corner at origin_mm.
// keep_cube(i,j,k) == false leaves that cube out (to make cavities).
inline TetMesh kuhn_box(const Eigen::Vector3d& origin_mm, std::array<int, 3> n, double h_mm,
                        const std::function<bool(int, int, int)>& keep_cube = nullptr) {
  TetMesh mesh;
  const auto node = [&](int i, int j, int k) { return i + (n[0] + 1) * (j + (n[1] + 1) * k); };
  for (int k = 0; k <= n[2]; ++k)
    for (int j = 0; j <= n[1]; ++j)
      for (int i = 0; i <= n[0]; ++i) mesh.nodes_mm.push_back(origin_mm + h_mm * Eigen::Vector3d(i, j, k));
  const std::array<std::array<int, 3>, 6> perms{
      {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}}};
  for (int k = 0; k < n[2]; ++k)
    for (int j = 0; j < n[1]; ++j)
      for (int i = 0; i < n[0]; ++i) {
        if (keep_cube && !keep_cube(i, j, k)) continue;
        for (const auto& p : perms) {
          std::array<int, 3> c{i, j, k};
          std::array<int, 4> tet{};
          tet[0] = node(c[0], c[1], c[2]);
          for (int s = 0; s < 3; ++s) {
            ++c[p[s]];
            tet[s + 1] = node(c[0], c[1], c[2]);
          }
          mesh.tets.push_back(tet);
          mesh.tet_labels.push_back(1);
          if (tet_volume_mm3(mesh, mesh.tets.size() - 1) < 0) std::swap(mesh.tets.back()[2], mesh.tets.back()[3]);
        }
      }
  return mesh;
}

// An oblique, anisotropic grid: rotation about z by angle_rad, then spacing.
inline Grid3 oblique_grid(std::array<int, 3> dims, const Eigen::Vector3d& spacing_mm,
                          const Eigen::Vector3d& origin_mm, double angle_rad) {
  Grid3 g;
  g.dims = dims;
  const Eigen::Matrix3d rot = Eigen::AngleAxisd(angle_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = rot * spacing_mm.asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = origin_mm;
  return g;
}

}  // namespace brainshift::test
