#pragma once
// Carrying preop surface models into the intraop configuration with the mesh
// deformation of one registration (engine/core/deformation.h).
//
// Preop phase (once per model and mesh): bind_to_mesh finds, for every model
// vertex, the preop tet containing it and its barycentric coordinates, using a
// uniform bucket grid over the tets' bounding boxes and precomputed inverse
// edge matrices.
// Vertices outside the mesh (a brain-surface vertex a fraction of a millimetre
// outside the meshed cortex, a ventricle vertex on the cavity side of the
// meshed wall, anything in a region that was not meshed) are bound to the
// CLOSEST POINT of the mesh boundary (faces used by a single tet, derived from
// the tets: outer surface and cavity walls), found through a bucket grid of
// those faces: they take the barycentrics of that point in its tet, i.e. the
// non-rigid residual is extended constantly along the shortest path to the
// mesh. Their affine part is still exact (A applied to the vertex itself).
//
// Per-scan phase: carry is a gather, x' = A p + sum_k lambda_k w_k, a few
// nanoseconds per vertex.
#include <array>
#include <cstddef>
#include <vector>

#include "core/deformation.h"
#include "core/tet_mesh.h"

namespace brainshift {

struct ModelBinding {
  std::vector<std::array<int, 4>> nodes;       // mesh nodes of each vertex's tet
  std::vector<std::array<double, 4>> weights;  // barycentrics (>= 0, sum 1)
  std::size_t mesh_node_count = 0;             // to reject a deformation of another mesh
  std::size_t vertices_outside = 0;            // bound to the closest mesh point
  double max_distance_outside_mm = 0;          // farthest such vertex from the mesh
};

// InputError if the mesh has no tets or the surface has non-finite vertices.
ModelBinding bind_to_mesh(const TriSurface& preop_model, const TetMesh& preop_mesh);

// The model in intraop world mm (same triangles; mesh_node cleared, the
// intraop vertices are no mesh nodes). InputError if the binding does not
// belong to this model or the deformation to the bound mesh.
TriSurface carry(const TriSurface& preop_model, const ModelBinding& binding,
                 const MeshDeformation& deformation);

}  // namespace brainshift
