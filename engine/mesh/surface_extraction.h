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

// The wall of the region of tets labelled `label` inside the tissue: faces
// between such a tet and a tet of another label, oriented out of the region
// (mesh-boundary faces are not included). Vertices in node order; mesh_node
// set as above. Sharp only where the mesher made `label` its own subdomain
// (MeshingParameters::interface_labels); otherwise it steps along tets.
TriSurface extract_interface_surface(const TetMesh& mesh, int label);

// Components connected through shared vertices.
std::size_t count_connected_components(const TriSurface& surface);

// Sorted unique nodes on any boundary face.
std::vector<int> boundary_nodes(const TetMesh& mesh);

// enclosed_volume_mm3(TriSurface) lives in core/tet_mesh.h.

}  // namespace brainshift
