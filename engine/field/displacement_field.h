#pragma once
// Dense pull-back displacement field on the intraop grid from a deformed
// tetrahedral mesh (see core/deformation.h for the frames and the convention
// x + u(x) = phi^-1(x)).
//
// Method:
//  1. Rasterisation. Every tet is mapped forward, q_k = phi(p_k), and scanned
//     over the intraop voxels it covers. phi is linear inside a tet (P1), so a
//     voxel centre x with barycentric coordinates lambda in the deformed tet
//     pulls back exactly to sum_k lambda_k p_k: u(x) = sum_k lambda_k p_k - x.
//     A voxel counts as inside when every lambda >= -barycentric_tolerance, so
//     faces shared by two tets leave no cracks; when several tets claim a voxel
//     (shared faces, or folded elements) the one in which the voxel lies deepest
//     (largest min lambda) wins, which makes the result independent of tet order.
//  2. Continuation. Write u = (A^-1 x - x) + r(x): the affine pull-back plus a
//     non-rigid remainder r, known on covered voxels. r is extended to the
//     uncovered voxels by push-pull pyramid inpainting followed by a few
//     Gauss-Seidel sweeps of the Laplace equation (covered voxels fixed) in the
//     cavities and within relax_band_mm of the brain region, so the field is
//     continuous across the mesh boundary and close to a harmonic fill inside
//     the ventricle cavities. (Farther out the pyramid's trilinear fill is
//     smooth enough and is faded out anyway; relaxing it there costs time.) The extension is faded out with distance d from the
//     "brain region" (covered voxels plus enclosed uncovered voxels, i.e.
//     cavities): weight = 1 - smoothstep(d / blend_distance_mm). Beyond
//     blend_distance_mm only the affine remains: u(x) = A^-1 x - x.
//     Enclosed cavities (uncovered voxels not 6-connected to the grid border)
//     keep the full non-rigid extension (weight 1). A cavity that reaches the
//     grid border (field of view cut through a ventricle) is treated as outside.
//     All of it runs on the covered voxels' bounding box grown by
//     max(blend_distance_mm, relax_band_mm) and a voxel, the affine alone
//     beyond: the work is the brain's neighbourhood, not the scan's field of
//     view, and the field does not depend on how far the grid extends beyond it.
#include <cstddef>
#include <nlohmann/json_fwd.hpp>

#include "core/deformation.h"
#include "core/image.h"
#include "core/tet_mesh.h"
#include "field/tissue_guard.h"
#include "image/morphology.h"

namespace brainshift {

struct FieldParameters {
  // Distance (mm) from the brain region over which the non-rigid part fades to 0.
  double blend_distance_mm = 10.0;
  // Barycentric slack for the inside test (dimensionless). Large enough to
  // absorb round-off on shared faces, small enough not to extrapolate visibly.
  double barycentric_tolerance = 1e-7;
  // Laplace sweeps after the pyramid fill (0 = pyramid only), and how far (mm)
  // outside the brain region they run (cavities are always relaxed).
  int smoothing_sweeps = 10;
  double relax_band_mm = 3.0;
};

struct FieldStats {
  std::size_t covered_voxels = 0;   // inside some deformed tet
  std::size_t cavity_voxels = 0;    // uncovered but enclosed by covered voxels
  std::size_t blended_voxels = 0;   // outside, 0 < weight < 1
  std::size_t skipped_tets = 0;     // degenerate after deformation (zero volume)
  std::size_t inverted_tets = 0;    // negative volume after deformation (folding)
  // The tissue guard (field/tissue_guard.h): voxels that pulled back into
  // preop tissue under the fade, voxels whose weight it raised, and voxels
  // that land in tissue even with the whole remainder.
  std::size_t guard_landing_voxels = 0;
  std::size_t guard_raised_voxels = 0;
  std::size_t guard_unresolved_voxels = 0;
  double rasterise_seconds = 0.0;
  double fill_seconds = 0.0;
  double total_seconds = 0.0;
};

// mesh_region, when given, receives the voxels the deformed mesh covers plus
// the enclosed cavities: where the field is the elastic solution's own map of
// the preop brain, not its extension (what the fold gate judges).
// guard, when given, keeps the extension from pulling preop tissue out of the
// brain (field/tissue_guard.h): the field a scan delivers.
// Throws InputError when deformation.nonrigid_mm does not have one vector per
// mesh node, a tet references a missing node, the grid is empty, or A is singular.
VectorImage3 pullback_field(const TetMesh& preop_mesh, const MeshDeformation& deformation,
                            const Grid3& intraop_grid, const FieldParameters& params,
                            FieldStats* stats = nullptr, Mask* mesh_region = nullptr,
                            const TissueGuard* guard = nullptr);

// nlohmann ADL hook (json j = stats;), for run reports.
void to_json(nlohmann::json& j, const FieldStats& s);

}  // namespace brainshift
