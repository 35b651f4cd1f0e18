#pragma once
// How far the served answer can be trusted, voxel by voxel: the radius (mm)
// of the 95 % band around the matched preop point x + u(x), on the intraop
// grid (uncertainty.nii.gz). It covers the brain with its cavities and one
// voxel beyond the segmented outline (which is only known to a voxel), and
// wherever the answer's warped preop labels put brain; 0 farther out, where
// no answer is claimed.
//
// Three independent sources, added in quadrature (DESIGN.md, "Uncertainty map";
// measured on the robustness suite, PERFORMANCE.md section 11):
//  1. The data's noise. The segmentation's quantisation, a uniform error over
//     a voxel: (voxel volume)^(1/3) / sqrt 12 RMS everywhere the answer is
//     claimed. And the match residual of each surface node (its distance to
//     the intraop boundary: what the match could not follow), optionally
//     (samples > 0; off by default, see UncertaintyParameters) propagated
//     through the elastic model by Monte Carlo: the noise is spatially
//     correlated like a segmenter's (random Fourier features of a Gaussian
//     process, correlation length noise_correlation_mm); the model is linear,
//     so a sample's effect on the field is the solve of the noise alone (one
//     warm pair of triangular solves). The node variance is carried to the
//     voxels through the mesh (barycentric, at the preop point of each voxel).
//  2. The model's own error: sqrt(|r| * resolution_mm * |grad r|), the
//     geometric mean of the local non-rigid displacement |r| and of its change
//     over the field's resolution (the image refinement's lattice). Large only
//     where both are: a large but uniform motion is pinned by the surface data
//     next to it, a steep but small variation moves little. With an image
//     that refined the field, image_residual_fraction of it remains.
//  3. Brain surface the field of view cut off (a slab, a short coil). The
//     match had no data there: each unseen surface node may have gone as far
//     as its distance from the seen surface, up to the largest brain shift
//     (unseen_shift_mm). Its effect inside is the elastic model's, the seen
//     surface held, in the worst direction (unseen_surface_rms_mm). It grows
//     away from the cut into the unseen brain and fades over the seen brain
//     as the model carries it; 0 when the whole brain is in view.
// The band radius is the 95 % quantile of a 3-D isotropic Gaussian error of
// that RMS: 2.80 / sqrt(3) = 1.61 times it.
#include <cstdint>
#include <functional>
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "core/image.h"
#include "core/tet_mesh.h"

namespace brainshift {

struct UncertaintyParameters {
  bool enabled = true;
  // Monte Carlo right-hand sides for the match residual's propagation; 0 =
  // not propagated. Off by default: on the robustness suite its part was not
  // where the error is (Spearman -0.09 with T1, -0.17 without) and added
  // outliers of up to 20 mm at badly matched nodes (DESIGN.md).
  int samples = 0;
  // The same for an affine-only answer (a refused non-rigid step): there the
  // residual is the shift the answer leaves uncorrected, the very error to
  // bound, and no model term exists (no non-rigid displacement).
  int fallback_samples = 12;
  double noise_correlation_mm = 10;   // correlation length of the surface noise
  // The length over which the field is resolved (the intensity refinement's
  // control lattice, 8 mm): the model's error scale per unit of strain.
  double resolution_mm = 8;
  // Of the model's error, the fraction an image refinement leaves: the ratio
  // of the robustness suite's mean TRE with and without the intraop T1
  // (0.43 / 0.81 mm, PERFORMANCE.md section 7).
  double image_residual_fraction = 0.53;
  // How far brain surface out of view may have moved unseen: the largest
  // cortical brain shift during surgery (5-20 mm at the cortex, up to 24 mm
  // measured). Not fitted: a safety bound (DESIGN.md, "Uncertainty map").
  double unseen_shift_mm = 20;
  double grid_spacing_mm = 3;         // the map is computed this coarse, then interpolated
  std::uint64_t seed = 19;
};

// Fixed-node values (in the FEM's fixed-node order) -> node displacements.
using LinearSolve = std::function<std::vector<Eigen::Vector3d>(const std::vector<Eigen::Vector3d>&)>;

// RMS (3-D) displacement at every mesh node caused by surface noise of RMS
// sigma_mm[i] at fixed node i (preop position fixed_preop_mm[i]).
std::vector<double> propagate_surface_noise(const std::vector<Eigen::Vector3d>& fixed_preop_mm,
                                            const std::vector<double>& sigma_mm, const LinearSolve& solve,
                                            const UncertaintyParameters& params);

// RMS (3-D) error at every mesh node caused by the fixed nodes marked unseen
// (unseen[i], fixed-node order; preop positions fixed_preop_mm) having moved
// unseen, the others held. How far: an unseen node at distance d from the
// nearest seen one by up to min(d, unseen_shift_mm): tissue cannot move
// relative to its neighbour by more than their distance without folding
// (|grad u| < 1), nor anywhere by more than the largest brain shift. In which
// direction: the worst one at each node, all unseen nodes together: per node
// the largest singular value of its 3x3 response to the three unit
// directions (three solves), as an RMS whose 95 % band is that size. Empty
// when no node is unseen (no solve).
std::vector<double> unseen_surface_rms_mm(const std::vector<Eigen::Vector3d>& fixed_preop_mm,
                                          const std::vector<bool>& unseen, const LinearSolve& solve,
                                          const UncertaintyParameters& params);

struct UncertaintyInput {
  const TetMesh& preop_mesh;
  const std::vector<double>& node_noise_rms_mm;  // propagate_surface_noise
  const VectorImage3& pullback_field_mm;         // the served field
  Eigen::Matrix4d intraop_from_preop;
  const LabelImage& intraop_labels;
  bool image_refined = false;                    // the intraop T1 refined the field's interior
  // The preop labels the answer carries onto the intraop grid (optional):
  // where they put brain the answer claims it too, even where the intraop
  // segmentation left it out (an image-only segmentation a few mm short).
  const LabelImage* warped_labels = nullptr;
};

// The 95 % band radius (mm) on the intraop grid; summary (optional) gets its
// statistics over the brain.
ImageF uncertainty_band_mm(const UncertaintyInput& in, const UncertaintyParameters& params,
                           nlohmann::json* summary = nullptr);

// The model-error RMS (mm) at a point: sqrt(|r| * resolution * |grad r|_F),
// r the non-rigid displacement (mm), grad r its Jacobian (dimensionless).
double model_error_rms_mm(double nonrigid_mm, double nonrigid_gradient, const UncertaintyParameters& params);

// 2.80 / sqrt(3): the 95 % radius of an isotropic 3-D Gaussian per unit of its RMS length.
inline constexpr double kBand95PerRms = 1.6140;

}  // namespace brainshift
