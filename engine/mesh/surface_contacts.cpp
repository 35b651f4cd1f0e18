// Ray shooting with CGAL's AABB tree; in its own translation unit because the
// CGAL headers are slow to compile (as label_mesher.cpp).
#include "mesh/surface_contacts.h"

#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/AABB_triangle_primitive.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <algorithm>

#include "core/errors.h"

namespace brainshift {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Triangle = Kernel::Triangle_3;
using Iterator = std::vector<Triangle>::const_iterator;
using Primitive = CGAL::AABB_triangle_primitive<Kernel, Iterator>;
using Tree = CGAL::AABB_tree<CGAL::AABB_traits<Kernel, Primitive>>;

Kernel::Point_3 point(const Eigen::Vector3d& p) { return {p.x(), p.y(), p.z()}; }

}  // namespace

std::vector<ContactPair> facing_vertex_pairs(const TriSurface& s, double max_gap_mm) {
  const int nv = static_cast<int>(s.vertices_mm.size());
  std::vector<Triangle> triangles;
  std::vector<int> source;  // surface triangle of each non-degenerate CGAL triangle
  for (std::size_t t = 0; t < s.triangles.size(); ++t) {
    const auto& tri = s.triangles[t];
    for (int v : tri)
      if (v < 0 || v >= nv) throw InputError("surface contacts: triangle index out of range");
    const Triangle T(point(s.vertices_mm[tri[0]]), point(s.vertices_mm[tri[1]]), point(s.vertices_mm[tri[2]]));
    if (T.is_degenerate()) continue;
    triangles.push_back(T);
    source.push_back(static_cast<int>(t));
  }
  std::vector<ContactPair> pairs;
  if (triangles.empty()) return pairs;
  const Tree tree(triangles.begin(), triangles.end());
  const auto normals = vertex_normals(s);
  for (int v = 0; v < nv; ++v) {
    if (normals[v].squaredNorm() == 0) continue;
    const Eigen::Vector3d& x = s.vertices_mm[v];
    // The triangles around v share it: a ray along the normal grazes them.
    const auto own = [&](const Iterator& it) {
      const auto& tri = s.triangles[static_cast<std::size_t>(source[static_cast<std::size_t>(it - triangles.begin())])];
      return tri[0] == v || tri[1] == v || tri[2] == v;
    };
    for (const double sign : {1.0, -1.0}) {
      const Eigen::Vector3d d = sign * normals[v];
      const auto hit = tree.first_intersection(Kernel::Ray_3(point(x), Kernel::Vector_3(d.x(), d.y(), d.z())), own);
      if (!hit) continue;
      const Kernel::Point_3* p = boost::get<Kernel::Point_3>(&hit->first);
      if (!p) continue;  // the ray runs inside a triangle's plane: no facing wall
      const Eigen::Vector3d h(p->x(), p->y(), p->z());
      const double gap = (h - x).norm();
      if (!(gap > 1e-6 && gap <= max_gap_mm)) continue;
      const auto& tri = s.triangles[static_cast<std::size_t>(source[static_cast<std::size_t>(hit->second - triangles.begin())])];
      int facing = tri[0];
      for (int w : tri)
        if ((s.vertices_mm[w] - h).squaredNorm() < (s.vertices_mm[facing] - h).squaredNorm()) facing = w;
      pairs.push_back({v, facing, d, gap});
    }
  }
  return pairs;
}

}  // namespace brainshift
