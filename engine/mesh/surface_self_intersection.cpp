// CGAL's box-intersection based self-intersection test (exact predicates),
// kept in its own translation unit like label_mesher.cpp because the CGAL
// headers are slow to compile.
#include "mesh/surface_self_intersection.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_mesh_processing/self_intersections.h>
#include <CGAL/Surface_mesh.h>

#include <algorithm>
#include <array>
#include <iterator>
#include <utility>
#include <vector>

#include "core/errors.h"

namespace brainshift {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Mesh = CGAL::Surface_mesh<Kernel::Point_3>;

// The boundary of a labeled tet mesh may be non-manifold (two parts of the
// cortex touching at a vertex or an edge), which Surface_mesh refuses. Such a
// face gets vertices of its own at the same positions; face i of the mesh is
// triangle i of the surface either way.
Mesh to_surface_mesh(const TriSurface& surface) {
  Mesh mesh;
  std::vector<Mesh::Vertex_index> v;
  v.reserve(surface.vertices_mm.size());
  auto point = [&](int i) {
    const auto& p = surface.vertices_mm[static_cast<std::size_t>(i)];
    return Kernel::Point_3(p.x(), p.y(), p.z());
  };
  for (std::size_t i = 0; i < surface.vertices_mm.size(); ++i) v.push_back(mesh.add_vertex(point(static_cast<int>(i))));
  for (const auto& t : surface.triangles) {
    for (int i : t)
      if (i < 0 || static_cast<std::size_t>(i) >= v.size()) throw InputError("surface: triangle index out of range");
    if (t[0] == t[1] || t[1] == t[2] || t[0] == t[2]) throw InputError("surface: a triangle repeats a vertex");
    if (mesh.add_face(v[t[0]], v[t[1]], v[t[2]]) != Mesh::null_face()) continue;
    if (mesh.add_face(mesh.add_vertex(point(t[0])), mesh.add_vertex(point(t[1])), mesh.add_vertex(point(t[2]))) ==
        Mesh::null_face())
      throw InputError("surface: a triangle cannot be added");
  }
  return mesh;
}

bool share_a_vertex(const std::array<int, 3>& a, const std::array<int, 3>& b) {
  for (int i : a)
    for (int j : b)
      if (i == j) return true;
  return false;
}

}  // namespace

std::vector<std::pair<int, int>> self_intersecting_triangle_pairs(const TriSurface& surface) {
  const Mesh mesh = to_surface_mesh(surface);
  std::vector<std::pair<Mesh::Face_index, Mesh::Face_index>> pairs;
  CGAL::Polygon_mesh_processing::self_intersections(mesh, std::back_inserter(pairs));
  // Faces split apart at a non-manifold vertex or edge still touch there: not
  // a crossing.
  std::vector<std::pair<int, int>> crossings;
  for (const auto& [f, g] : pairs) {
    const int a = static_cast<int>(f.idx()), b = static_cast<int>(g.idx());
    if (!share_a_vertex(surface.triangles[static_cast<std::size_t>(a)], surface.triangles[static_cast<std::size_t>(b)]))
      crossings.emplace_back(std::min(a, b), std::max(a, b));
  }
  return crossings;
}

std::size_t count_self_intersections(const TriSurface& surface) {
  return self_intersecting_triangle_pairs(surface).size();
}

}  // namespace brainshift
