#pragma once
// Structured tet meshes of a box for FEM tests: each hex cell is split into
// the 6 Kuhn tets that share its main diagonal. Every cell uses the same
// split, so faces between cells match and the mesh is conforming. Nodes are
// numbered x fastest, then y, then z.
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <vector>

#include "core/tet_mesh.h"

namespace brainshift::test {

struct BoxMesh {
  TetMesh mesh;
  std::vector<int> boundary_nodes;  // on any face of the box
  std::vector<int> interior_nodes;
};

// cells[i] cells along axis i; the box spans [origin, origin + size]. Tets with
// centroid x below the mid-plane get label_low, the others label_high.
inline BoxMesh make_box_mesh(std::array<int, 3> cells, Eigen::Vector3d origin_mm,
                             Eigen::Vector3d size_mm, int label_low = 1, int label_high = 2) {
  BoxMesh box;
  TetMesh& m = box.mesh;
  const int nx = cells[0] + 1, ny = cells[1] + 1, nz = cells[2] + 1;
  auto id = [&](int i, int j, int k) { return i + nx * (j + ny * k); };
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const Eigen::Vector3d t(double(i) / cells[0], double(j) / cells[1], double(k) / cells[2]);
        m.nodes_mm.push_back(origin_mm + t.cwiseProduct(size_mm));
        const bool on_face = i == 0 || j == 0 || k == 0 || i == nx - 1 || j == ny - 1 || k == nz - 1;
        (on_face ? box.boundary_nodes : box.interior_nodes).push_back(id(i, j, k));
      }
  const double mid_x = origin_mm.x() + 0.5 * size_mm.x();
  std::array<int, 3> axes{0, 1, 2};
  for (int k = 0; k < cells[2]; ++k)
    for (int j = 0; j < cells[1]; ++j)
      for (int i = 0; i < cells[0]; ++i) {
        std::sort(axes.begin(), axes.end());
        do {  // one tet per monotone path corner 000 -> 111 of the cell
          std::array<int, 3> at{i, j, k};
          std::array<int, 4> tet;
          tet[0] = id(at[0], at[1], at[2]);
          for (int s = 0; s < 3; ++s) {
            ++at[axes[s]];
            tet[s + 1] = id(at[0], at[1], at[2]);
          }
          m.tets.push_back(tet);
          if (tet_volume_mm3(m, m.tets.size() - 1) < 0) std::swap(m.tets.back()[2], m.tets.back()[3]);
          const Eigen::Vector3d centroid = 0.25 * (m.nodes_mm[tet[0]] + m.nodes_mm[tet[1]] +
                                                   m.nodes_mm[tet[2]] + m.nodes_mm[tet[3]]);
          m.tet_labels.push_back(centroid.x() < mid_x ? label_low : label_high);
        } while (std::next_permutation(axes.begin(), axes.end()));
      }
  return box;
}

}  // namespace brainshift::test
