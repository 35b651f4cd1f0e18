#pragma once
// Boundary surfaces of a TetMesh (outer brain surface, cavity walls) as
// triangle surfaces tied to mesh nodes, for surface matching and models.
#include <cstddef>
#include <vector>

#include "core/tet_mesh.h"

namespace brainshift {

inline constexpr int kAnyBoundary = -1;

// Boundary faces whose neighbour_label equals `neighbour_label` (kAnyBoundary:
// all of them). Vertices are the used mesh nodes in increasing node order;
// mesh_node[v] is the TetMesh node of vertex v. Triangles keep the outward
// orientation of the boundary faces.
TriSurface extract_boundary_surface(const TetMesh& mesh, int neighbour_label);

// Components connected through shared vertices.
std::size_t count_connected_components(const TriSurface& surface);

// Sorted unique nodes on any boundary face.
std::vector<int> boundary_nodes(const TetMesh& mesh);

// enclosed_volume_mm3(TriSurface) lives in core/tet_mesh.h.

}  // namespace brainshift
