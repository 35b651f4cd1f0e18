#include "mesh/surface_extraction.h"

#include <algorithm>
#include <array>
#include <numeric>

namespace brainshift {

namespace {

// A surface of the given mesh faces (node triples), vertices in node order.
TriSurface surface_of_faces(const TetMesh& mesh, const std::vector<std::array<int, 3>>& faces) {
  std::vector<int> vertex_of(mesh.node_count(), -1);
  std::vector<char> used(mesh.node_count(), 0);
  for (const auto& f : faces)
    for (int n : f) used[n] = 1;
  TriSurface s;
  for (std::size_t n = 0; n < used.size(); ++n)
    if (used[n]) {
      vertex_of[n] = static_cast<int>(s.vertices_mm.size());
      s.vertices_mm.push_back(mesh.nodes_mm[n]);
      s.mesh_node.push_back(static_cast<int>(n));
    }
  for (const auto& f : faces) s.triangles.push_back({vertex_of[f[0]], vertex_of[f[1]], vertex_of[f[2]]});
  return s;
}

// Face `opposite` of tet t (the face without that local vertex), ordered so
// its normal points out of the tet.
std::array<int, 3> outward_face_of(const TetMesh& mesh, std::size_t t, int opposite) {
  static constexpr int kFace[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};
  const auto& n = mesh.tets[t];
  return {n[kFace[opposite][0]], n[kFace[opposite][1]], n[kFace[opposite][2]]};
}

}  // namespace

TriSurface extract_boundary_surface(const TetMesh& mesh, int neighbour_label) {
  std::vector<std::array<int, 3>> faces;
  for (const auto& f : mesh.boundary_faces)
    if (neighbour_label == kAnyBoundary || f.neighbour_label == neighbour_label) faces.push_back(f.nodes);
  return surface_of_faces(mesh, faces);
}

TriSurface extract_interface_surface(const TetMesh& mesh, int label) {
  // Every face of a `label` tet, keyed by its sorted nodes; a face seen from a
  // tet of another label is on the interface. Faces on the mesh boundary have
  // no second tet and are not part of it.
  struct Face {
    std::array<int, 3> key;
    std::size_t tet;
    int opposite;
  };
  std::vector<Face> faces;
  for (std::size_t t = 0; t < mesh.tet_count(); ++t)
    for (int f = 0; f < 4; ++f) {
      std::array<int, 3> key = outward_face_of(mesh, t, f);
      std::sort(key.begin(), key.end());
      faces.push_back({key, t, f});
    }
  std::sort(faces.begin(), faces.end(), [](const Face& a, const Face& b) { return a.key < b.key; });
  std::vector<std::array<int, 3>> wall;
  for (std::size_t i = 0; i + 1 < faces.size(); ++i) {
    if (faces[i].key != faces[i + 1].key) continue;
    const Face& a = faces[i];
    const Face& b = faces[i + 1];
    const bool a_in = mesh.tet_labels[a.tet] == label, b_in = mesh.tet_labels[b.tet] == label;
    if (a_in != b_in) {
      const Face& inside = a_in ? a : b;
      wall.push_back(outward_face_of(mesh, inside.tet, inside.opposite));
    }
    ++i;
  }
  return surface_of_faces(mesh, wall);
}

std::size_t count_connected_components(const TriSurface& surface) {
  std::vector<int> parent(surface.vertices_mm.size());
  std::iota(parent.begin(), parent.end(), 0);
  auto find = [&](int v) {
    while (parent[v] != v) v = parent[v] = parent[parent[v]];
    return v;
  };
  std::vector<char> used(parent.size(), 0);
  for (const auto& t : surface.triangles) {
    for (int v : t) used[v] = 1;
    parent[find(t[1])] = find(t[0]);
    parent[find(t[2])] = find(t[0]);
  }
  std::size_t roots = 0;
  for (std::size_t v = 0; v < parent.size(); ++v)
    if (used[v] && find(static_cast<int>(v)) == static_cast<int>(v)) ++roots;
  return roots;
}

std::vector<int> boundary_nodes(const TetMesh& mesh) {
  std::vector<int> nodes;
  for (const auto& f : mesh.boundary_faces) nodes.insert(nodes.end(), f.nodes.begin(), f.nodes.end());
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  return nodes;
}

}  // namespace brainshift
