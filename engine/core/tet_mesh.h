#pragma once
// The labeled tetrahedral mesh shared by meshing, FEM, registration and I/O.
#include <Eigen/Dense>
#include <array>
#include <vector>

namespace brainshift {

// Which surface a boundary triangle belongs to: the label of the region on the
// other side of it. 0 = outside the brain (outer brain surface); the ventricle
// label = the wall of the lateral-ventricle cavity.
struct BoundaryFace {
  std::array<int, 3> nodes;  // ordered so the normal points out of the mesh
  int neighbour_label = 0;
};

struct TetMesh {
  std::vector<Eigen::Vector3d> nodes_mm;  // world RAS+ mm
  std::vector<std::array<int, 4>> tets;   // positively oriented (volume > 0)
  std::vector<int> tet_labels;            // tissue label of each tet (material)
  std::vector<BoundaryFace> boundary_faces;

  std::size_t node_count() const { return nodes_mm.size(); }
  std::size_t tet_count() const { return tets.size(); }
};

// Signed volume (mm^3); positive for a positively oriented tet.
inline double tet_volume_mm3(const TetMesh& m, std::size_t t) {
  const auto& n = m.tets[t];
  const Eigen::Vector3d a = m.nodes_mm[n[1]] - m.nodes_mm[n[0]];
  const Eigen::Vector3d b = m.nodes_mm[n[2]] - m.nodes_mm[n[0]];
  const Eigen::Vector3d c = m.nodes_mm[n[3]] - m.nodes_mm[n[0]];
  return a.dot(b.cross(c)) / 6.0;
}

// A triangulated surface. For surfaces taken from a TetMesh, mesh_node holds
// the TetMesh node of each vertex, so surface displacements map to Dirichlet
// values directly.
struct TriSurface {
  std::vector<Eigen::Vector3d> vertices_mm;
  std::vector<std::array<int, 3>> triangles;  // outward-facing
  std::vector<int> mesh_node;                 // empty when not tied to a mesh
};

// Sum over triangles of (centroid . normal * area) / 3: the enclosed volume
// (divergence theorem) when the surface is closed and outward-facing; negative
// when it faces inward (a cavity wall seen from the tissue).
inline double enclosed_volume_mm3(const TriSurface& surface) {
  double volume = 0;
  for (const auto& t : surface.triangles)
    volume += surface.vertices_mm[t[0]].dot(surface.vertices_mm[t[1]].cross(surface.vertices_mm[t[2]])) / 6.0;
  return volume;
}

// Per-vertex unit normals: the area-weighted mean of the incident triangles'
// normals, so they point the way the triangles face (outward for a model).
// A vertex no triangle uses gets (0, 0, 0).
inline std::vector<Eigen::Vector3d> vertex_normals(const TriSurface& surface) {
  std::vector<Eigen::Vector3d> normals(surface.vertices_mm.size(), Eigen::Vector3d::Zero());
  for (const auto& t : surface.triangles) {
    const Eigen::Vector3d& a = surface.vertices_mm[t[0]];
    // |cross| is twice the area: the sum is area-weighted without a division.
    const Eigen::Vector3d n = (surface.vertices_mm[t[1]] - a).cross(surface.vertices_mm[t[2]] - a);
    for (int v : t) normals[v] += n;
  }
  for (auto& n : normals) {
    const double length = n.norm();
    if (length > 0) n /= length;
  }
  return normals;
}

}  // namespace brainshift
