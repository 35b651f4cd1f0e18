#pragma once
// Whether a triangulated surface passes through itself. After the active
// surface match a self-intersecting brain or ventricle surface means the match
// went wrong (two parts of the cortex pulled through each other): its
// displacements must not drive the FEM (a quality gate, see DESIGN.md).
#include <cstddef>
#include <utility>
#include <vector>

#include "core/tet_mesh.h"

namespace brainshift {

// Number of pairs of triangles that intersect other than along the edge or
// vertex they share (CGAL exact predicates). 0 for an embedded surface.
// Non-manifold vertices and edges (a labeled mesh's boundary may have them)
// are accepted. Throws InputError for an index out of range or a degenerate
// triangle (one vertex used twice).
std::size_t count_self_intersections(const TriSurface& surface);

// The crossing pairs themselves (triangle indices, first < second, sorted),
// same rules. A surface of at least min_faces_to_split triangles is checked
// in two halves side by side (surface_self_intersection.cpp): the same pairs.
// Below it (a ventricle wall) the second thread would cost more than it saves.
inline constexpr std::size_t kMinFacesToSplitCheck = 4096;
std::vector<std::pair<int, int>> self_intersecting_triangle_pairs(const TriSurface& surface,
                                                                  std::size_t min_faces_to_split = kMinFacesToSplitCheck);

}  // namespace brainshift
