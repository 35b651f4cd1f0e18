#include "mesh/mesh_quality.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace brainshift {
namespace {

constexpr double kDegenerateRelativeVolume = 1e-8;  // same rule as mesh assembly

double radius_edge_ratio(const std::array<Eigen::Vector3d, 4>& p) {
  const Eigen::Vector3d a = p[1] - p[0], b = p[2] - p[0], c = p[3] - p[0];
  const double denom = 2.0 * a.dot(b.cross(c));
  if (denom == 0) return std::numeric_limits<double>::infinity();
  const Eigen::Vector3d centre_offset =
      (a.squaredNorm() * b.cross(c) + b.squaredNorm() * c.cross(a) + c.squaredNorm() * a.cross(b)) / denom;
  double shortest = std::numeric_limits<double>::infinity();
  for (int i = 0; i < 4; ++i)
    for (int j = i + 1; j < 4; ++j) shortest = std::min(shortest, (p[i] - p[j]).norm());
  return centre_offset.norm() / shortest;
}

}  // namespace

std::array<double, 6> dihedral_angles_deg(const TetMesh& mesh, std::size_t tet) {
  const auto& t = mesh.tets[tet];
  std::array<Eigen::Vector3d, 4> p;
  for (int i = 0; i < 4; ++i) p[i] = mesh.nodes_mm[t[i]];
  // The dihedral angle at edge (i,j) lies between the two faces holding it,
  // i.e. the faces opposite the other two vertices k and l.
  static constexpr int edges[6][2] = {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}};
  std::array<double, 6> out{};
  for (int e = 0; e < 6; ++e) {
    const int i = edges[e][0], j = edges[e][1];
    int k = -1, l = -1;
    for (int m = 0; m < 4; ++m)
      if (m != i && m != j) (k < 0 ? k : l) = m;
    const Eigen::Vector3d axis = (p[j] - p[i]).normalized();
    Eigen::Vector3d u = p[k] - p[i], v = p[l] - p[i];
    u -= u.dot(axis) * axis;
    v -= v.dot(axis) * axis;
    const double cosine = std::clamp(u.normalized().dot(v.normalized()), -1.0, 1.0);
    out[e] = std::acos(cosine) * 180.0 / M_PI;
  }
  return out;
}

MeshQuality measure_quality(const TetMesh& mesh) {
  MeshQuality q;
  q.nodes = mesh.node_count();
  q.tets = mesh.tet_count();
  q.boundary_faces = mesh.boundary_faces.size();
  if (mesh.tets.empty()) return q;
  q.min_dihedral_deg = 180;
  q.min_volume_mm3 = std::numeric_limits<double>::infinity();
  for (std::size_t t = 0; t < mesh.tets.size(); ++t) {
    std::array<Eigen::Vector3d, 4> p;
    for (int i = 0; i < 4; ++i) p[i] = mesh.nodes_mm[mesh.tets[t][i]];
    const double v = tet_volume_mm3(mesh, t);
    double longest = 0;
    for (int i = 0; i < 4; ++i)
      for (int j = i + 1; j < 4; ++j) longest = std::max(longest, (p[i] - p[j]).norm());
    if (v < 0) ++q.inverted_tets;
    if (!(std::abs(v) >= kDegenerateRelativeVolume * longest * longest * longest)) ++q.degenerate_tets;
    q.min_volume_mm3 = std::min(q.min_volume_mm3, v);
    q.total_volume_mm3 += v;
    q.max_radius_edge_ratio = std::max(q.max_radius_edge_ratio, radius_edge_ratio(p));
    for (double a : dihedral_angles_deg(mesh, t)) {
      q.min_dihedral_deg = std::min(q.min_dihedral_deg, a);
      q.max_dihedral_deg = std::max(q.max_dihedral_deg, a);
    }
  }
  return q;
}

}  // namespace brainshift
