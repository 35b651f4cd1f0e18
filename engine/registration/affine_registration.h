#pragma once
// 12-parameter affine registration of the preop label map to the intraop one.
//
// Cost: points on the preop structure boundaries (the brain outline and the
// ventricle wall), mapped by the affine x = A p + t, are scored by the intraop
// signed distance map of the same structure:
//   C(A,t) = sum_s  w_s / N_s  sum_i rho_c( D_s(A p_i + t) )
// with rho_c the Geman-McClure loss (quadratic below c, saturating at c^2/2
// above): brain shift moves part of the surface by 5-20 mm, and a redescending
// loss lets those points stop pulling on the affine instead of dragging it.
// Points mapped outside the intraop grid score the saturated loss c^2/2, so the
// optimiser cannot lower the cost by pushing points out of the field of view.
//
// Minimiser: Levenberg-Marquardt on iteratively reweighted least squares, with
// the analytic Jacobian (trilinear distance-map gradient times d x / d params).
// Schedule: a SIMILARITY (rotation, translation, isotropic scale: 7
// parameters) coarse to fine, few points and a wide robust scale first (large
// capture range), then more points and tighter scales; then the full affine
// from it at the finest level, with the robust scale taken from the data (a
// multiple of the MAD sigma of the residuals). A similarity cannot shear
// toward a 25 mm local sink, and by the time the affine's extra freedom is
// switched on the sunken points are far outside the robust scale. Initialisation from moments (centroids; isotropic scale from
// the volume ratio), plus the principal-axes rotation as a second candidate
// when both covariances have well separated eigenvalues, plus the cheapest of
// a sweep of 108 head poses when it is another pose (a head turned for a
// lateral approach); each candidate runs the coarse level and the lowest cost
// wins.
#include <cstdint>
#include <string>

#include <Eigen/Dense>

#include "core/image.h"
#include "registration/boundary_samples.h"

namespace brainshift {

struct AffineRegistrationParameters {
  int levels = 3;                   // coarse-to-fine stages (>= 1)
  int coarse_points = 1500;         // outline points used at the coarsest level
  int fine_points = 20000;          // ... at the finest level (geometric in between)
  int iterations_per_level = 50;    // LM iterations cap per level
  double robust_scale_mm = 1.0;     // Geman-McClure c at the finest level
  double coarse_scale_factor = 2.5; // c multiplies by this per coarser level
  double brain_weight = 1.0;        // weight of the outline term (normalised by its point count)
  double ventricle_weight = 0.5;    // weight of the ventricle-wall term (0 disables it)
  // A level has converged when the last update moved every sample point by
  // less than this (mm).
  double tolerance_mm = 0.002;
  double coarse_tolerance_mm = 0.05;
  // Principal axes are used as a candidate only when adjacent eigenvalues of
  // both covariances differ by at least this ratio (otherwise the axes are
  // ill-defined and the candidate would be noise).
  double principal_axes_min_eigen_ratio = 1.1;
  // Fit quality below which the result is reported as not converged: fraction
  // of finest-level points within 2 x robust_scale_mm of the intraop surface.
  double min_inlier_fraction = 0.5;
  // The affine stage's robust scale: data_scale_factor x the MAD sigma of the
  // finest-level residuals after the similarity, clamped to
  // [min_robust_scale_mm, robust_scale_mm]. 2.5 sigma keeps ~99 % of Gaussian
  // segmentation noise in the quadratic part of the loss; 0.5 mm is half the
  // finest voxel a segmentation resolves (below it the distance map's own
  // interpolation error dominates).
  double data_scale_factor = 2.5;
  double min_robust_scale_mm = 0.5;
  bool affine_stage = true;  // false: the similarity is the result
  // The full affine replaces the similarity only when its MAD sigma is at
  // most this fraction of the similarity's: anisotropy and shear that are
  // real shift every outline point and lower the median residual; the
  // flanks of a local sink are a minority and barely move it. 1 = always
  // (the default: on an 18 mm vertex sink the similarity left the whole sink
  // to the elastic field, which folded; see docs/DESIGN.md).
  double max_affine_sigma_ratio = 1.0;
};

struct AffineRegistrationResult {
  Eigen::Matrix4d intraop_from_preop = Eigen::Matrix4d::Identity();
  int iterations = 0;             // LM iterations over all levels (final candidate)
  // A plausible matrix (determinant in (0.5, 2)) that fits the data
  // (inlier_fraction >= min_inlier_fraction, 30 % of the points in view).
  // An LM stopped by its iteration cap at such a fit is converged.
  bool converged = false;
  // The determinant alone in (0.5, 2): a head's volume, whatever the fit. An
  // affine outside it is not a head moving but labels that are not the
  // preop's brain (a brain segmented in part, another scan's).
  bool plausible = false;
  bool tolerance_met = false;     // the last LM step was below tolerance_mm (reported only)
  double initial_cost = 0;        // at the moment-based initialisation, finest-level cost
  double final_cost = 0;          // same cost at the result
  double rms_surface_distance_mm = 0;  // over finest-level points inside the intraop grid
  double inlier_fraction = 0;          // of those points, |distance| < 2c
  std::size_t points_used = 0;         // finest-level points inside the intraop grid
  double residual_sigma_mm = 0;        // MAD sigma of the residuals after the similarity
  double robust_scale_mm = 0;          // the affine stage's Geman-McClure c
  bool affine_kept = false;            // the full affine replaced the similarity
  std::string message;                 // human-readable summary, says why when not converged
};

// Throws InputError when either map lacks brain_label or is empty. Never throws
// for a hard case: converged is false and message explains.
AffineRegistrationResult register_affine(const LabelImage& preop_labels,
                                         const LabelImage& intraop_labels,
                                         const AffineRegistrationParameters& params,
                                         std::uint16_t brain_label = 1,
                                         std::uint16_t ventricle_label = 2);

// The same on prepared inputs (see boundary_samples.h). start (optional): a
// warm start, the answer of a registration of a nearly identical intraop
// segmentation (the image-only path's re-match, docs/DESIGN.md "Automatic
// intraop segmentation" item 9), within a voxel or two of this one: only the
// finest level runs, from it (the coarse levels and the moment candidates
// are there for capture range), then the full affine as usual.
// candidate (optional, without start): one more start for the coarse level
// beside the moments' (identity and principal axes) and the pose sweep's
// (a head turned in its clamp, see the .cpp), the lowest cost winning: where
// the head was placed on the scan (the image-only path). Like the sweep's,
// only when more than 15 degrees from every other start.
AffineRegistrationResult register_affine(const PreopBoundarySamples& preop,
                                         const IntraopDistanceMaps& intraop,
                                         const AffineRegistrationParameters& params,
                                         const Eigen::Matrix4d* start = nullptr,
                                         const Eigen::Matrix4d* candidate = nullptr);

// The parameters of a placement: an affine that only has to bring a
// structure within a search's width (millimetres: a fluid space several mm
// across), not to the outline's own accuracy. A quarter of the finest
// level's points, at most two levels: the twelve parameters stay fixed by
// thousands of points, at about a quarter of the time (docs/PERFORMANCE.md
// 12.33 and 12.39).
AffineRegistrationParameters placement_affine(const AffineRegistrationParameters& full);

}  // namespace brainshift
