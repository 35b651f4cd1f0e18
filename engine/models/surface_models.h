#pragma once
// Triangulated models of preop structures (brain, ventricles, corticospinal
// tract, tumour) for display and navigation, built from a label map.
//
// Method: the binary mask of the structure is blurred lightly (Gaussian,
// presmooth_sigma_mm) so that its 0.5 level lies at sub-voxel accurate
// positions, then contoured with marching tetrahedra on the Kuhn (Freudenthal)
// split of every voxel cube. Marching tetrahedra has no ambiguous cases, so the
// surface is always a closed, orientable 2-manifold (every edge is shared by
// exactly two triangles); marching cubes tables cannot promise that on binary
// data. The price is more, and thinner, triangles: edges much shorter than a
// voxel are collapsed (keeping the manifold), then a Taubin lambda/mu
// smoothing (which does not shrink, unlike plain Laplacian smoothing) relaxes
// the triangles.
//
// Vertices are in world RAS+ mm (labels.grid.world_from_voxel, oblique or
// flipped); triangles are ordered so that their normals point out of the
// structure in world space, also when the affine flips handedness.
// A structure thinner than about one voxel may vanish in the blur.
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "core/image.h"
#include "core/tet_mesh.h"

namespace brainshift {

struct ModelParameters {
  // Gaussian blur of the binary mask before contouring, in mm per axis (an axis
  // whose spacing makes sigma < 0.25 voxel is not blurred).
  double presmooth_sigma_mm = 0.7;
  // Edges shorter than this fraction of the smallest voxel spacing are
  // collapsed (topology-preserving) before smoothing: marching tetrahedra
  // leaves many tiny triangles where the surface grazes grid points. 0 = off.
  double min_edge_fraction = 0.4;
  // Taubin smoothing: each iteration is one lambda (shrink) and one mu
  // (inflate) umbrella step with uniform weights.
  int taubin_iterations = 15;
  double taubin_lambda = 0.5;
  double taubin_mu = -0.53;
};

// The surface of {voxels whose label is in `labels_in_structure`}. Empty
// surface when no voxel has those labels. InputError on an empty image or
// bad parameters.
TriSurface surface_model(const LabelImage& labels,
                         const std::vector<std::uint16_t>& labels_in_structure,
                         const ModelParameters& params = {});
TriSurface surface_model(const LabelImage& labels, std::uint16_t label,
                         const ModelParameters& params = {});

// A named structure and the labels that form it.
struct StructureDefinition {
  std::string name;
  std::vector<std::uint16_t> labels;
};

// (Made from the label table by the pipeline: the parenchyma's structure
// holds every label inside it, so its surface is the outer brain surface.)
// One model per structure present in the label map (absent ones are skipped).
std::map<std::string, TriSurface> structure_models(
    const LabelImage& labels, const std::vector<StructureDefinition>& table,
    const ModelParameters& params = {});

// Geometry checks used by tests and by callers that validate models.
double surface_area_mm2(const TriSurface& surface);
// True when every undirected edge is used by exactly two triangles, and in
// opposite directions (closed and consistently oriented).
bool is_closed_oriented_manifold(const TriSurface& surface);

}  // namespace brainshift
