// CGAL's box-intersection based self-intersection test (exact predicates),
// kept in its own translation unit like label_mesher.cpp because the CGAL
// headers are slow to compile.
#include "mesh/surface_self_intersection.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_mesh_processing/self_intersections.h>
#include <CGAL/Surface_mesh.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <iterator>
#include <limits>
#include <utility>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"

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

// The faces in two halves at the median of their centroids along the
// surface's longest axis, and the faces whose extent along that axis reaches
// within the longest face's extent of the median (the slab). Two triangles
// that cross share a point, so their extents overlap: a crossing pair with
// one face in each half has both faces in the slab (each centroid lies
// within a face's extent of that shared point). The pairs within each half
// and within the slab are therefore every pair.
struct FaceSplit {
  std::vector<Mesh::Face_index> lower, upper, slab;
};

FaceSplit split_at_median(const TriSurface& surface) {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  for (const auto& p : surface.vertices_mm) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  int axis = 0;
  (hi - lo).maxCoeff(&axis);
  const std::size_t n = surface.triangles.size();
  std::vector<double> centroid(n), low(n), high(n);
  double longest = 0;
  for (std::size_t f = 0; f < n; ++f) {
    const auto& t = surface.triangles[f];
    const double a = surface.vertices_mm[t[0]][axis], b = surface.vertices_mm[t[1]][axis],
                 c = surface.vertices_mm[t[2]][axis];
    centroid[f] = (a + b + c) / 3;
    low[f] = std::min({a, b, c});
    high[f] = std::max({a, b, c});
    longest = std::max(longest, high[f] - low[f]);
  }
  std::vector<double> sorted = centroid;
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(n / 2), sorted.end());
  const double median = sorted[n / 2];
  // A rounding's margin: a centroid may come out an ulp beyond its face.
  const double reach = longest + 1e-9 * (1 + std::abs(median) + longest);
  FaceSplit split;
  for (std::size_t f = 0; f < n; ++f) {
    const Mesh::Face_index face(static_cast<Mesh::size_type>(f));
    (centroid[f] < median ? split.lower : split.upper).push_back(face);
    if (high[f] >= median - reach && low[f] <= median + reach) split.slab.push_back(face);
  }
  return split;
}

}  // namespace

std::vector<std::pair<int, int>> self_intersecting_triangle_pairs(const TriSurface& surface,
                                                                  std::size_t min_faces_to_split) {
  const Mesh mesh = to_surface_mesh(surface);
  using FacePairs = std::vector<std::pair<Mesh::Face_index, Mesh::Face_index>>;
  std::array<FacePairs, 2> found;
  namespace PMP = CGAL::Polygon_mesh_processing;
  if (surface.triangles.size() < std::max<std::size_t>(min_faces_to_split, 2)) {
    PMP::self_intersections(mesh, std::back_inserter(found[0]));
  } else {
    // The box intersection is the check's whole cost and serial: the two
    // halves side by side (the slab with the upper half), the same pairs.
    const FaceSplit split = split_at_median(surface);
    parallel_halves(2, 1, [&](std::size_t begin, std::size_t end) {
      for (std::size_t h = begin; h < end; ++h) {
        auto out = std::back_inserter(found[h]);
        if (h == 0) {
          PMP::self_intersections(split.lower, mesh, out);
        } else {
          PMP::self_intersections(split.upper, mesh, out);
          PMP::self_intersections(split.slab, mesh, out);
        }
      }
    });
  }
  // Faces split apart at a non-manifold vertex or edge still touch there: not
  // a crossing.
  std::vector<std::pair<int, int>> crossings;
  for (const auto& pairs : found)
    for (const auto& [f, g] : pairs) {
      const int a = static_cast<int>(f.idx()), b = static_cast<int>(g.idx());
      if (!share_a_vertex(surface.triangles[static_cast<std::size_t>(a)], surface.triangles[static_cast<std::size_t>(b)]))
        crossings.emplace_back(std::min(a, b), std::max(a, b));
    }
  std::sort(crossings.begin(), crossings.end());
  crossings.erase(std::unique(crossings.begin(), crossings.end()), crossings.end());
  return crossings;
}

std::size_t count_self_intersections(const TriSurface& surface) {
  return self_intersecting_triangle_pairs(surface).size();
}

}  // namespace brainshift
