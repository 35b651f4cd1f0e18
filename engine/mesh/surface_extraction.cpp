#include "mesh/surface_extraction.h"

#include <algorithm>
#include <numeric>

namespace brainshift {

TriSurface extract_boundary_surface(const TetMesh& mesh, int neighbour_label) {
  std::vector<int> vertex_of(mesh.node_count(), -1);
  std::vector<char> used(mesh.node_count(), 0);
  auto selected = [&](const BoundaryFace& f) {
    return neighbour_label == kAnyBoundary || f.neighbour_label == neighbour_label;
  };
  for (const auto& f : mesh.boundary_faces)
    if (selected(f))
      for (int n : f.nodes) used[n] = 1;
  TriSurface s;
  for (std::size_t n = 0; n < used.size(); ++n)
    if (used[n]) {
      vertex_of[n] = static_cast<int>(s.vertices_mm.size());
      s.vertices_mm.push_back(mesh.nodes_mm[n]);
      s.mesh_node.push_back(static_cast<int>(n));
    }
  for (const auto& f : mesh.boundary_faces)
    if (selected(f)) s.triangles.push_back({vertex_of[f.nodes[0]], vertex_of[f.nodes[1]], vertex_of[f.nodes[2]]});
  return s;
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
