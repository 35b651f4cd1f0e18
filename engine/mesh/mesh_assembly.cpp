#include "mesh/mesh_assembly.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>

#include "core/errors.h"

namespace brainshift {
namespace {

double signed_volume(const std::vector<Eigen::Vector3d>& x, const std::array<int, 4>& t) {
  return (x[t[1]] - x[t[0]]).dot((x[t[2]] - x[t[0]]).cross(x[t[3]] - x[t[0]])) / 6.0;
}

double longest_edge(const std::vector<Eigen::Vector3d>& x, const std::array<int, 4>& t) {
  double longest = 0;
  for (int a = 0; a < 4; ++a)
    for (int b = a + 1; b < 4; ++b) longest = std::max(longest, (x[t[a]] - x[t[b]]).norm());
  return longest;
}

// Spreads the low 21 bits of v so that two zero bits separate each bit.
std::uint64_t spread_bits(std::uint64_t v) {
  v &= 0x1fffff;
  v = (v | v << 32) & 0x1f00000000ffffULL;
  v = (v | v << 16) & 0x1f0000ff0000ffULL;
  v = (v | v << 8) & 0x100f00f00f00f00fULL;
  v = (v | v << 4) & 0x10c30c30c30c30c3ULL;
  v = (v | v << 2) & 0x1249249249249249ULL;
  return v;
}

int material_label(const Eigen::Vector3d& centroid_mm, const LabelImage& labels, const AssemblyOptions& o) {
  const Eigen::Vector4d ijk = labels.grid.voxel_from_world() * centroid_mm.homogeneous();
  const int i = static_cast<int>(std::lround(ijk.x())), j = static_cast<int>(std::lround(ijk.y())),
            k = static_cast<int>(std::lround(ijk.z()));
  if (!labels.grid.contains(i, j, k)) return o.default_tissue_label;
  const std::uint16_t l = labels.at(i, j, k);
  const bool cavity = std::find(o.cavity_labels.begin(), o.cavity_labels.end(), l) != o.cavity_labels.end();
  const bool interface =
      std::find(o.interface_labels.begin(), o.interface_labels.end(), l) != o.interface_labels.end();
  return (l == 0 || cavity || interface) ? o.default_tissue_label : l;
}

// Node order: `(b - a) x (c - a)` must point away from the tet's fourth node.
std::array<int, 3> outward_face(const std::vector<Eigen::Vector3d>& x, const std::array<int, 4>& tet,
                                int opposite_local) {
  std::array<int, 3> f{};
  for (int a = 0, n = 0; a < 4; ++a)
    if (a != opposite_local) f[n++] = tet[a];
  const Eigen::Vector3d normal = (x[f[1]] - x[f[0]]).cross(x[f[2]] - x[f[0]]);
  if (normal.dot(x[f[0]] - x[tet[opposite_local]]) < 0) std::swap(f[1], f[2]);
  return f;
}

// Clears keep[] for every tet outside the face-connected piece of largest
// volume; returns how many were cleared.
std::size_t keep_only_largest_piece(const RawTetMesh& raw, std::vector<char>& keep) {
  const std::size_t nt = raw.tets.size();
  std::vector<std::pair<std::array<int, 3>, int>> faces;
  for (std::size_t t = 0; t < nt; ++t)
    if (keep[t])
      for (int f = 0; f < 4; ++f) {
        std::array<int, 3> key{};
        for (int a = 0, n = 0; a < 4; ++a)
          if (a != f) key[n++] = raw.tets[t][a];
        std::sort(key.begin(), key.end());
        faces.emplace_back(key, static_cast<int>(t));
      }
  std::sort(faces.begin(), faces.end());
  std::vector<int> parent(nt);
  std::iota(parent.begin(), parent.end(), 0);
  auto find = [&](int v) {
    while (parent[v] != v) v = parent[v] = parent[parent[v]];
    return v;
  };
  for (std::size_t i = 1; i < faces.size(); ++i)
    if (faces[i].first == faces[i - 1].first) parent[find(faces[i].second)] = find(faces[i - 1].second);
  std::vector<double> volume(nt, 0.0);
  for (std::size_t t = 0; t < nt; ++t)
    if (keep[t]) volume[find(static_cast<int>(t))] += std::abs(signed_volume(raw.nodes_mm, raw.tets[t]));
  const int largest = static_cast<int>(std::max_element(volume.begin(), volume.end()) - volume.begin());
  std::size_t dropped = 0;
  for (std::size_t t = 0; t < nt; ++t)
    if (keep[t] && find(static_cast<int>(t)) != largest) keep[t] = 0, ++dropped;
  return dropped;
}

}  // namespace

std::vector<int> morton_order(const std::vector<Eigen::Vector3d>& points) {
  std::vector<int> order(points.size());
  std::iota(order.begin(), order.end(), 0);
  if (points.empty()) return order;
  Eigen::Vector3d lo = points[0], hi = points[0];
  for (const auto& p : points) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  const double extent = std::max((hi - lo).maxCoeff(), 1e-12);
  const double scale = double((1 << 21) - 1) / extent;  // same scale on all axes keeps cells cubic
  std::vector<std::uint64_t> key(points.size());
  for (std::size_t n = 0; n < points.size(); ++n) {
    const Eigen::Vector3d q = (points[n] - lo) * scale;
    key[n] = spread_bits(std::uint64_t(q.x())) | spread_bits(std::uint64_t(q.y())) << 1 |
             spread_bits(std::uint64_t(q.z())) << 2;
  }
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return key[a] < key[b]; });
  return order;
}

TetMesh assemble_tet_mesh(RawTetMesh raw, const LabelImage& labels, const AssemblyOptions& options,
                          AssemblyReport* report) {
  const auto& x = raw.nodes_mm;
  std::vector<char> keep(raw.tets.size(), 1);
  std::size_t dropped = 0;
  for (std::size_t t = 0; t < raw.tets.size(); ++t) {
    for (int n : raw.tets[t])
      if (n < 0 || n >= static_cast<int>(x.size())) throw ComputeError("assemble_tet_mesh: tet node out of range");
    const double v = signed_volume(x, raw.tets[t]);
    const double l = longest_edge(x, raw.tets[t]);
    if (!(std::abs(v) >= options.degenerate_relative_volume * l * l * l)) keep[t] = 0, ++dropped;
  }
  const std::size_t islands = options.keep_largest_component ? keep_only_largest_piece(raw, keep) : 0;
  if (report) *report = {dropped, islands};

  // Faces first, from the raw tets, before any renumbering.
  std::vector<BoundaryFace> faces;
  for (const auto& b : raw.boundary)
    if (keep.at(b.tet)) faces.push_back({outward_face(x, raw.tets[b.tet], b.opposite_local), b.neighbour_label});

  // Renumber the used nodes along the Morton curve.
  std::vector<int> used;
  {
    std::vector<char> is_used(x.size(), 0);
    for (std::size_t t = 0; t < raw.tets.size(); ++t)
      if (keep[t])
        for (int n : raw.tets[t]) is_used[n] = 1;
    for (std::size_t n = 0; n < x.size(); ++n)
      if (is_used[n]) used.push_back(static_cast<int>(n));
  }
  std::vector<Eigen::Vector3d> used_points;
  for (int n : used) used_points.push_back(x[n]);
  const std::vector<int> order = morton_order(used_points);
  std::vector<int> new_of_old(x.size(), -1);
  TetMesh mesh;
  for (std::size_t n = 0; n < order.size(); ++n) {
    new_of_old[used[order[n]]] = static_cast<int>(n);
    mesh.nodes_mm.push_back(x[used[order[n]]]);
  }

  struct Tet { std::array<int, 4> nodes; int label; };
  std::vector<Tet> tets;
  for (std::size_t t = 0; t < raw.tets.size(); ++t) {
    if (!keep[t]) continue;
    Tet tet{};
    for (int a = 0; a < 4; ++a) tet.nodes[a] = new_of_old[raw.tets[t][a]];
    if (signed_volume(mesh.nodes_mm, tet.nodes) < 0) std::swap(tet.nodes[2], tet.nodes[3]);
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    for (int n : tet.nodes) centroid += mesh.nodes_mm[n] / 4.0;
    const bool forced = t < raw.forced_labels.size() && raw.forced_labels[t] >= 0;
    tet.label = forced ? raw.forced_labels[t] : material_label(centroid, labels, options);
    tets.push_back(tet);
  }
  // Sorted by smallest node (then the rest) so each rank's tets are contiguous
  // and the order is canonical.
  auto sorted_key = [](std::array<int, 4> n) { std::sort(n.begin(), n.end()); return n; };
  std::sort(tets.begin(), tets.end(), [&](const Tet& a, const Tet& b) { return sorted_key(a.nodes) < sorted_key(b.nodes); });
  for (const auto& t : tets) {
    mesh.tets.push_back(t.nodes);
    mesh.tet_labels.push_back(t.label);
  }

  for (auto& f : faces)
    for (int& n : f.nodes) n = new_of_old[n];
  auto face_key = [](const BoundaryFace& f) {
    std::array<int, 4> k{f.nodes[0], f.nodes[1], f.nodes[2], 0};
    std::sort(k.begin(), k.begin() + 3);
    k[3] = f.neighbour_label;
    return k;
  };
  std::sort(faces.begin(), faces.end(), [&](const BoundaryFace& a, const BoundaryFace& b) { return face_key(a) < face_key(b); });
  mesh.boundary_faces = std::move(faces);
  return mesh;
}

}  // namespace brainshift
