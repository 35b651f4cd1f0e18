// CGAL's box-intersection based self-intersection test (exact predicates),
// kept in its own translation unit like label_mesher.cpp because the CGAL
// headers are slow to compile.
#include "mesh/surface_self_intersection.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_mesh_processing/self_intersections.h>
#include <CGAL/Surface_mesh.h>

#include <iterator>
#include <utility>
#include <vector>

#include "core/errors.h"

namespace brainshift {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Mesh = CGAL::Surface_mesh<Kernel::Point_3>;

Mesh to_surface_mesh(const TriSurface& surface) {
  Mesh mesh;
  std::vector<Mesh::Vertex_index> v;
  v.reserve(surface.vertices_mm.size());
  for (const auto& p : surface.vertices_mm) v.push_back(mesh.add_vertex(Kernel::Point_3(p.x(), p.y(), p.z())));
  for (const auto& t : surface.triangles) {
    for (int i : t)
      if (i < 0 || static_cast<std::size_t>(i) >= v.size()) throw InputError("surface: triangle index out of range");
    if (mesh.add_face(v[t[0]], v[t[1]], v[t[2]]) == Mesh::null_face())
      throw InputError("surface: the triangles do not form a manifold polygon mesh");
  }
  return mesh;
}

}  // namespace

std::size_t count_self_intersections(const TriSurface& surface) {
  const Mesh mesh = to_surface_mesh(surface);
  std::vector<std::pair<Mesh::Face_index, Mesh::Face_index>> pairs;
  CGAL::Polygon_mesh_processing::self_intersections(mesh, std::back_inserter(pairs));
  return pairs.size();
}

}  // namespace brainshift
