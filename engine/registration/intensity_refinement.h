#pragma once
// Intensity-based refinement of the brain's interior after the elastic solve.
//
// Why: the FEM gets boundary data only from the outer brain surface and the
// ventricle walls; the tissue in between follows the elastic model, which
// with perfect boundary data still leaves 0.4-1.3 mm (docs/PERFORMANCE.md
// section 3). The intraop T1 carries the interior's own evidence (grey/white
// matter edges, deep nuclei, the ventricle walls as the scanner sees them).
//
// What: a smooth correction v moves the intraop point before the FEM's
// pull-back u maps it (x + u(x) is the preop point): u'(x) = v(x) + u(x + v(x)),
// with v chosen so that the preop T1 at x + u'(x) matches the intraop T1 at
// x up to a smooth intensity bias and a transfer function:
//   I(x) ~ b(x) f(P(x + u'(x))) + d
// I intraop image, P preop T1 (trilinear), b a low-order polynomial over the
// brain (receive-coil bias and the scanners' different global scales), d a
// constant (noise floor, black level), f the identity for a T1 or a smooth
// 1-D function estimated from the data for another contrast (T2-like, a
// compressed low-field T1; see intensity_bias.h). v is trilinear on a coarse control
// lattice aligned with the intraop voxel axes (isotropic spacing in mm); it is
// used inside the brain region and fades to 0 outside it, where the field is
// the FEM's continuation that fades to the affine. Composed rather than
// added, the Jacobian determinants multiply and the correction cannot fold
// an element the FEM compressed strongly (see intensity_correction.cpp).
// The optimisation linearises u(x + v) ~ u(x) + grad u(x) v at each sample;
// the final composition is exact.
//
// Cost (Gauss-Newton with iteratively reweighted least squares):
//   sum_s w_s rho(r_s / sigma)                      image, robust (Geman-McClure)
//   + l^2 k density * int |grad v|^2 dV              smoothness over l = smoothing_length_mm
//   + (l / L)^2 k density * int |v|^2 dV             trust the FEM where the image is silent (L: fem_trust_length_mm)
// density = samples per mm^3 and k the data term's mean curvature per sample
// (1/mm^2), so the balance between the image and the priors depends neither
// on how many samples are drawn nor on the image's noise and contrast. The
// samples are intraop tissue voxels (not ventricles, background or a
// resection cavity), those with the strongest preop gradient first,
// down-weighted near the outer boundary and near background/cavity voxels:
// there the intraop intensity (fluid in a gap or cavity, dura, skull) does
// not follow the brain. The preop is compared at the intraop scanner's
// resolution (match_point_spread).
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "core/image.h"

namespace brainshift {

struct IntensityRefinementParameters {
  bool enabled = true;
  // Control lattice spacing (mm). The elastic model's interior error varies
  // over centimetres (it comes from boundary data far away); 8 mm resolves
  // that with ~10-20 samples per cell and stays far above the scale of the
  // image noise. (6 and 10 mm give the same accuracy on the phantom suite.)
  double lattice_spacing_mm = 8.0;
  // Gauss-Newton iterations at most (each one pass over the samples); stops
  // earlier when no node moves by more than convergence_mm.
  int iterations = 10;
  double convergence_mm = 0.01;
  // The regulariser, as lengths relative to the data term's mean curvature
  // at the start (what one sample tells of the motion; noise, blur and a
  // weak contrast lower it): the image decides motion features longer than
  // smoothing_length_mm, the lattice limits the rest; where the image is
  // silent v fades back to the FEM's answer over fem_trust_length_mm. The
  // same on any scanner: fixed weights against a data term normalised by the
  // noise made a 0.15 T scan (SNR 7, curvature 0.2 / mm^2) eight times stiffer
  // than a 1.5 T one (1.55 / mm^2). 3.6 mm is the length the fixed weights
  // below had on the 1.5 T scan. Raised where the image's noise would move v
  // by more than its grid's position uncertainty (voxel / sqrt(12)).
  // docs/DESIGN.md "Interior refinement from the intraop T1".
  double smoothing_length_mm = 3.6;
  double fem_trust_length_mm = 30.0;
  // Compare the intraop image with the preop blurred to the intraop voxel's
  // point-spread function (a box in-plane, a slice profile of FWHM one slice
  // across), not with the sharp preop: at 2-3 mm slices partial volume
  // otherwise reads as misalignment (0.15 T cases 0.03-0.07 mm closer,
  // docs/PERFORMANCE.md 9.1). A blurred copy of the preop (about 0.15 s of
  // work); the caller may keep it for the next scan on a grid of the same
  // resolution (IntensityRefinementInput::preop_t1_at_resolution).
  bool match_point_spread = true;
  // Used only with smoothing_length_mm = 0: fixed weights, against the data
  // term normalised by its residual spread. Membrane weight (dimensionless);
  // pull toward v = 0 (1/mm^2), v decays over sqrt(membrane / shrink) ~ 30 mm.
  double membrane_weight = 20.0;
  double shrink_weight_per_mm2 = 0.02;
  // Bounds on the correction v (mm, the move of the intraop point; the change
  // of u can be somewhat larger where the FEM stretches the tissue): the
  // surfaces already agree with the segmentation; the image refines the
  // interior, it does not replace the model. max_step_mm is a trust region
  // per Gauss-Newton step (the trilinear preop image is only linear within a
  // voxel).
  double max_correction_mm = 3.0;
  double max_step_mm = 1.0;
  // Sampling: candidates on a grid of about this spacing (mm), at most
  // max_samples of them kept, strongest preop gradient first (about a
  // quarter of the brain's candidates; the time per iteration is linear in it).
  double sample_spacing_mm = 2.0;
  std::size_t max_samples = 40000;
  // Samples closer than half this to the outer boundary or to a background
  // or cavity voxel are dropped, weight ramps to 1 at this distance (mm):
  // ~2-3x the segmentation's boundary noise.
  double boundary_margin_mm = 4.0;
  // Geman-McClure scale in units of the robust residual spread (1.4826 MAD):
  // residuals far beyond it (fluid where tissue was, a lesion) stop pulling.
  double robust_scale = 3.0;
  // Degree of the multiplicative bias polynomial b (0 = global scale only).
  int bias_degree = 2;
  // Distance (mm) outside the brain region over which v fades to 0.
  double outside_fade_mm = 8.0;
  // The stage is skipped (the FEM's field kept) when the intensity model
  // (linear, or through a transfer function f for another contrast)
  // explains less than this share of the intraop intensity variance left by
  // a smooth trend of position alone, at the start: an image unrelated to the
  // preop carries no trustworthy motion. Measured (test_intensity_refinement):
  // pure noise 0.002, the same head 30 mm away 0.02, a T2-like image 0.93;
  // (brainshift_refine_bench, plain R^2) the phantom suite 0.84-0.96, with
  // noise of 10 / 25 / 40 % of the brain's p99 added 0.6 / 0.23 / 0.1, where
  // the refinement still lowers the TRE (0.56 / 0.78 / 0.89 against 0.96 mm).
  // Why and how in docs/DESIGN.md "Interior refinement from the intraop T1".
  double min_explained_variance = 0.1;
};

// What is wrong with the parameters, naming the key ("" when they are valid),
// and the same as an InputError.
std::string validation_error(const IntensityRefinementParameters& p);
void validate(const IntensityRefinementParameters& p);

struct IntensityRefinementInput {
  const ImageF& intraop_t1;          // on the field's grid
  const LabelImage& intraop_labels;  // on the field's grid
  // Signed distance (mm) to the intraop brain region (all labels, enclosed
  // holes filled), negative inside; on the field's grid.
  const ImageF& brain_sdf_mm;
  const ImageF& preop_t1;  // any grid, world RAS+ mm
  // Labels whose voxels are tissue that moves with the brain and is sampled.
  std::vector<std::uint16_t> tissue_labels;
  // Label of voxels whose intensity does not follow the brain (outside, a
  // resection cavity): samples keep boundary_margin_mm away from them.
  std::uint16_t background_label = 0;
  // With match_point_spread: the preop T1 already blurred to the field
  // grid's resolution (preop_at_intraop_resolution for a grid of the same
  // preop_point_spread_sigma_voxels); null: made here.
  const ImageF* preop_t1_at_resolution = nullptr;
};

// The blur, in preop voxels per preop axis, that takes the preop T1 to what a
// scanner with `intraop`'s voxels records (match_point_spread): grids of the
// same spacing and axes give the same blur, and so the same blurred preop.
Eigen::Vector3d preop_point_spread_sigma_voxels(const Grid3& preop, const Grid3& intraop);

// The preop T1 blurred by preop_point_spread_sigma_voxels(preop.grid, intraop).
ImageF preop_at_intraop_resolution(const ImageF& preop, const Grid3& intraop);

struct IntensityRefinementReport {
  bool applied = false;
  std::string skipped_reason;  // when not applied
  int iterations = 0;
  std::size_t candidates = 0, samples = 0, bias_samples = 0;
  // RMS of the intensity residual over the samples, relative to the median
  // intraop tissue intensity: with v = 0 and after the refinement.
  double rms_residual_before = 0, rms_residual_after = 0;
  double max_correction_mm = 0, mean_correction_mm = 0;  // |u' - u| inside the brain region
  std::string bias_model;
  double explained_variance = 0;  // weighted R^2 of the bias model's fit
  // What one sample tells of the motion at the start (mean data curvature
  // per axis, 1/mm^2; noise and blur lower it).
  double data_curvature_per_mm2 = 0;
  double smoothing_length_mm = 0;  // in force (raised by the noise floor; 0: fixed weights)
  double seconds = 0;  // whole stage; and its parts:
  double sampling_seconds = 0, optimise_seconds = 0, apply_seconds = 0;
};

void to_json(nlohmann::json& j, const IntensityRefinementReport& r);

// Adds the correction to pullback_mm in place. The report says why nothing
// was done when too few samples exist; InputError when the inputs' grids
// disagree or the parameters are invalid.
IntensityRefinementReport refine_with_intensity(VectorImage3& pullback_mm, const IntensityRefinementInput& input,
                                                const IntensityRefinementParameters& p);

}  // namespace brainshift
