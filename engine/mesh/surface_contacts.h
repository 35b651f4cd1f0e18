#pragma once
// Facing walls of one surface: the two walls of a thin ventricular horn, the
// two banks of a narrow sulcus, the two sides of the septum between the
// lateral ventricles. A surface match must not push such walls through each
// other (registration/active_surface.h keeps every pair's approach below a
// fraction of its gap: self-contact), so the pairs are found once, on the
// preop surface, by shooting a ray from every vertex along and against its
// normal and taking the first triangle it hits (CGAL AABB tree).
#include <vector>

#include <Eigen/Dense>

#include "core/surface_contact.h"
#include "core/tet_mesh.h"

namespace brainshift {

// Pairs with gap_mm <= max_gap_mm. Rays ignore the triangles around their own
// vertex. InputError for triangle indices out of range.
std::vector<ContactPair> facing_vertex_pairs(const TriSurface& surface, double max_gap_mm);

}  // namespace brainshift
