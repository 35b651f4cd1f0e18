#pragma once
// Active-surface matching: an elastic membrane attached to a surface (the preop
// brain outline or ventricle wall, already mapped by the affine into the
// intraop frame) is pulled onto the zero level of an intraop signed distance
// map. The membrane acts on the DISPLACEMENT u of the vertices, not on their
// positions, so the shape is kept and only non-smooth motion is penalised.
//
// Continuous model: minimise  E(u) = 1/2 int D(x0+u)^2 dA + alpha/2 int |grad_S u|^2 dA,
// D the target signed distance, grad_S the surface gradient. Discretised with
// P1 finite elements on the triangle mesh: lumped mass matrix M (area / 3 per
// vertex) and the cotangent stiffness matrix K (positive semi-definite for any
// triangulation). Semi-implicit gradient flow with step tau and the force
//     f = -D (n . n_D) n      (n the current vertex normal, n_D the unit
// distance-map gradient; negative alignment counts as 0): the step onto the
// zero level along the surface normal. Normal-only forces keep the trilinear
// gradient's cell-to-cell direction jumps from pushing vertices sideways.
//     (M + tau*alpha*K) u_{k+1} = M (u_k + tau * clip(f_k))
// The matrix is factorised once (SimplicialLDLT). At the fixed point
// alpha*K u = M f: with f ~ d - u (d the true normal offset) the result is the
// membrane-filtered target, u = (M + alpha K)^-1 M d, i.e. alpha (mm^2) is the
// square of a smoothing length. Components of wavelength lambda are attenuated
// by 1 / (1 + alpha (2 pi / lambda)^2): alpha = 8 mm^2 keeps ~95 % of an 80 mm
// wavelength (a ~40 mm wide sinking) and removes ~95 % of 4 mm wavelength
// (about 1-voxel) segmentation noise. Measured: an 8 mm Gaussian dent of 15 mm
// width is followed to 7.3 mm at its centre; 1.2 mm lattice noise leaves a
// mean error of 0.12 mm (0.28 mm with a floppy membrane). The stiffness is a
// continuous operator (mesh-independent), so the same alpha works for the
// 17k-vertex outline and the 3k-vertex ventricles. The optional intensity edge
// force (intraop_image) adds edge_weight * (offset of the strongest intensity
// step along n within +-edge_search_mm) * n.
//
// Convergence: the largest update ALONG THE VERTEX NORMALS stays below
// convergence_tolerance_mm for convergence_iterations consecutive iterations.
// That is the matched shape; smooth tangential modes keep relaxing slowly
// (normal forces give the membrane no tangential pull) and are not waited for:
// they slide vertices along the surface (measured <= 1.9 mm at the flanks of
// an 8 mm dent) without changing it.
// Self-contact: after every step the approach of each facing-wall pair,
// (u_a - u_b) . d, is cut back to contact_fraction x its gap, half from each
// side (a few Gauss-Seidel sweeps, as a vertex can be in several pairs).
// Large motion without folding (a 20-25 mm sink, a 7 mm retractor dent):
//  - continuation over the stiffness: stiffness_levels membranes, the first
//    stiffness_ratio^(levels-1) x alpha, each stiffness_ratio softer, the last
//    alpha itself. A stiff membrane follows the wide motion (the sink) and
//    cannot follow a narrow dent or noise, so it cannot fold; the softer ones
//    then add the detail from a start that is already close. Each level's
//    membrane acts on what it adds to the previous levels' displacement
//    (iterated Tikhonov), so the final stiffness smooths the detail without
//    pulling the wide motion back.
//  - the fold guard in the flow (FoldGuard, surface_repair.h): after every
//    step, the vertices of a triangle whose normal would turn past the bound
//    from the input surface, or whose area would collapse, take a shorter
//    step. The flow starts unfolded and each step keeps it so: where the
//    normal force would crush triangles (the rim of a steep dent) the
//    membrane is held, locally stiffer, instead of folding.
// Folding check: a triangle whose normal turned by more than 90 degrees from
// the input surface (or collapsed to zero area) is counted as flipped.
#include <cstddef>
#include <string>
#include <vector>

#include <Eigen/Dense>

#include "core/image.h"
#include "core/surface_contact.h"
#include "core/tet_mesh.h"
#include "registration/surface_repair.h"

namespace brainshift {

struct ActiveSurfaceParameters {
  int max_iterations = 80;
  double step = 1.0;                     // tau in (0, 1]; 1 = a full projection step each iteration
  double membrane_stiffness = 8.0;       // alpha, mm^2 (see above)
  double convergence_tolerance_mm = 0.01;
  int convergence_iterations = 2;
  double max_step_mm = 2.0;              // force clipped per iteration (avoids jumping to a far surface)
  // Gaussian-like smoothing (sigma, mm) of the force along the surface before
  // the membrane solve: damps the cell-to-cell jumps of the trilinear gradient.
  double force_smoothing_mm = 1.0;
  // Intensity edge force (only when an intraop image is given): weight of the
  // pull toward the strongest intensity edge along the vertex normal, searched
  // within +-edge_search_mm. Small: the label map is the primary evidence.
  double edge_weight = 0.2;
  double edge_search_mm = 2.0;
  // Self-contact: two facing walls of the surface (a thin horn's walls, a
  // narrow sulcus's banks; ContactPair) may close at most this fraction of
  // the gap between them, so they never pass through each other. Below 0.5
  // each wall keeps to its half.
  double contact_fraction = 0.4;
  // Capture range (mm; 0 = unlimited): a vertex farther than this from the
  // target's zero level gets no force and follows its neighbours. A part of a
  // structure the segmenter missed (a thin horn) is then not dragged onto the
  // nearest other wall. Only for surfaces whose motion beyond the affine is
  // small (the ventricles); the cortex under a craniotomy moves 20 mm.
  double capture_range_mm = 0.0;
  // Normal search (mm; 0 = off): a vertex farther than 0.5 mm from the target
  // is pulled to the first zero crossing of the distance map along its normal
  // within this range, when that crossing is at most 3 |d| + 1 mm away (else
  // the distance force above): it enters a narrow dent, whose floor the
  // nearest-surface distance does not see.
  double normal_search_mm = 0.0;
  // Continuation over the membrane stiffness (see above); 1 = alpha only.
  // Each level runs up to max_iterations.
  int stiffness_levels = 1;
  double stiffness_ratio = 4.0;
  bool fold_guard_enabled = true;
  FoldGuard fold_guard;
};

struct SurfaceMatchResult {
  // Per vertex, intraop frame: from the input (affine-mapped) position to the
  // matched position.
  std::vector<Eigen::Vector3d> displacement_mm;
  // |signed distance| at the final position; NaN for vertices outside the
  // target image (no data there: they follow their neighbours through the membrane).
  std::vector<double> residual_distance_mm;
  double mean_residual_mm = 0, max_residual_mm = 0;  // over vertices with data
  std::size_t vertices_without_data = 0;
  int iterations = 0;
  bool converged = false;
  std::size_t flipped_triangles = 0;
  // Vertices whose step the fold guard shortened in the last iteration, and
  // the largest such count over the flow.
  std::size_t guarded_vertices_last = 0, guarded_vertices_max = 0;
  double seconds = 0;
  std::string message;
};

// Throws InputError for an empty surface, out-of-range triangle indices,
// invalid parameters or an empty target image. Never throws for a poor match:
// converged / flipped_triangles / message report it.
// contacts: facing-wall pairs of the surface (optional); their approach is
// projected back after every step.
SurfaceMatchResult match_surface(const TriSurface& surface_in_intraop_frame,
                                 const ImageF& target_signed_distance_mm,
                                 const ActiveSurfaceParameters& params,
                                 const ImageF* intraop_image = nullptr,
                                 const ContactPairs* contacts = nullptr);

}  // namespace brainshift
