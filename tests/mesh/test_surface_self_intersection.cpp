// The self-intersection check behind the surface-match quality gate.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

#include "core/errors.h"
#include "mesh/surface_self_intersection.h"

using namespace brainshift;

namespace {

// A closed, outward-facing sphere: an octahedron subdivided `levels` times.
TriSurface sphere(double radius_mm, const Eigen::Vector3d& centre, int levels) {
  TriSurface s;
  s.vertices_mm = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}};
  s.triangles = {{0, 2, 4}, {2, 1, 4}, {1, 3, 4}, {3, 0, 4}, {2, 0, 5}, {1, 2, 5}, {3, 1, 5}, {0, 3, 5}};
  for (int l = 0; l < levels; ++l) {
    std::map<std::pair<int, int>, int> midpoint;
    auto mid = [&](int a, int b) {
      const auto key = std::minmax(a, b);
      if (auto it = midpoint.find(key); it != midpoint.end()) return it->second;
      s.vertices_mm.push_back((s.vertices_mm[a] + s.vertices_mm[b]).normalized());
      return midpoint[key] = static_cast<int>(s.vertices_mm.size()) - 1;
    };
    std::vector<std::array<int, 3>> finer;
    for (const auto& t : s.triangles) {
      const int ab = mid(t[0], t[1]), bc = mid(t[1], t[2]), ca = mid(t[2], t[0]);
      finer.insert(finer.end(), {{t[0], ab, ca}, {ab, t[1], bc}, {ca, bc, t[2]}, {ab, bc, ca}});
    }
    s.triangles = std::move(finer);
  }
  for (auto& v : s.vertices_mm) v = centre + radius_mm * v.normalized();
  return s;
}

}  // namespace

TEST(SurfaceSelfIntersection, AnEmbeddedSphereHasNone) {
  const TriSurface s = sphere(50, {1, 2, 3}, 3);
  ASSERT_EQ(s.triangles.size(), 512u);
  EXPECT_EQ(count_self_intersections(s), 0u);
  EXPECT_GT(enclosed_volume_mm3(s), 0.0);
}

TEST(SurfaceSelfIntersection, AVertexPulledThroughTheFarSideIsFound) {
  TriSurface s = sphere(50, {0, 0, 0}, 3);
  // The north pole dragged through the south pole: its fan crosses the far side.
  for (auto& v : s.vertices_mm)
    if (v.z() > 49.9) v = {0, 0, -80};
  EXPECT_GT(count_self_intersections(s), 0u);
}

TEST(SurfaceSelfIntersection, AFoldThatDoesNotCrossIsNotAnIntersection) {
  TriSurface s = sphere(50, {0, 0, 0}, 3);
  // A deep dent (the pole pushed inwards to 10 mm from the centre) stays embedded.
  for (auto& v : s.vertices_mm)
    if (v.z() > 49.9) v = {0, 0, 10};
  EXPECT_EQ(count_self_intersections(s), 0u);
}

// A labeled mesh's boundary may be non-manifold (parts touching at a vertex
// or an edge): it is still checked, and touching is not crossing.
TEST(SurfaceSelfIntersection, NonManifoldSurfacesAreChecked) {
  TriSurface s = sphere(50, {0, 0, 0}, 1);
  s.triangles.push_back(s.triangles.front());  // an edge used by three faces
  EXPECT_EQ(count_self_intersections(s), 0u);
  // Two spheres through each other, one of them with the non-manifold face.
  const TriSurface other = sphere(50, {60, 0, 0}, 1);
  const int offset = static_cast<int>(s.vertices_mm.size());
  s.vertices_mm.insert(s.vertices_mm.end(), other.vertices_mm.begin(), other.vertices_mm.end());
  for (const auto& t : other.triangles) s.triangles.push_back({t[0] + offset, t[1] + offset, t[2] + offset});
  EXPECT_GT(count_self_intersections(s), 0u);
}

TEST(SurfaceSelfIntersection, InvalidTrianglesAreAnInputError) {
  TriSurface s = sphere(50, {0, 0, 0}, 1);
  s.triangles.push_back({0, 1, 999});
  EXPECT_THROW(count_self_intersections(s), InputError);
  s.triangles.back() = {0, 0, 1};
  EXPECT_THROW(count_self_intersections(s), InputError);
}

// The check of a large surface runs in two halves split at a median plane
// (and the faces near it): it must find exactly the pairs the whole check
// finds, crossings on either side of the plane and across it alike.
TEST(SurfaceSelfIntersection, TheCheckInTwoHalvesFindsTheSamePairs) {
  TriSurface s = sphere(50, {3, -2, 1}, 5);
  ASSERT_EQ(s.triangles.size(), 8192u);
  // Three crossings: the +x pole pulled through the -x side (which also makes
  // x the longest axis, the one split at its median), and two patches near
  // that median pushed through the opposite side (from +z and from -y):
  // their crossing pairs have a face on each side of the split.
  for (auto& v : s.vertices_mm) {
    const Eigen::Vector3d d = v - Eigen::Vector3d(3, -2, 1);
    if (d.x() > 49.5) v.x() -= 130;
    if (d.z() > 49.0 && d.y() > 0) v.z() -= 95;
    if (std::abs(d.x()) < 4 && d.y() < -48.5) v.y() += 99;
  }
  const auto whole = self_intersecting_triangle_pairs(s, std::numeric_limits<std::size_t>::max());
  const auto halves = self_intersecting_triangle_pairs(s, 0);
  ASSERT_GT(whole.size(), 30u);
  EXPECT_EQ(halves, whole);
  EXPECT_TRUE(std::is_sorted(whole.begin(), whole.end()));
  // And an embedded surface has none either way.
  const TriSurface ball = sphere(50, {0, 0, 0}, 5);
  EXPECT_TRUE(self_intersecting_triangle_pairs(ball, 0).empty());
}
