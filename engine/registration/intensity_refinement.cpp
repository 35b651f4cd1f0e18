#include "registration/intensity_refinement.h"

#include <algorithm>
#include <cmath>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/errors.h"
#include "core/timer.h"
#include "image/gaussian_smooth.h"
#include "registration/intensity_correction.h"
#include "registration/intensity_lattice.h"
#include "registration/intensity_robust.h"
#include "registration/intensity_samples.h"
#include "registration/intensity_solver.h"
#include "registration/linear_sampler.h"

// The stages live beside this file, one concept each: intensity_lattice
// (the control lattice and the region it covers), intensity_samples,
// intensity_bias (the model b P + d and the trust in it), intensity_solver
// (Gauss-Newton) and intensity_correction (the composition with the FEM's
// field). This file validates and runs them in order.
namespace brainshift {
namespace {

using namespace intensity;

void check_inputs(const VectorImage3& u, const IntensityRefinementInput& in) {
  const Grid3& g = u.grid;
  if (g.dims[0] < 2 || g.dims[1] < 2 || g.dims[2] < 2 || u.vectors.size() != g.voxel_count())
    throw InputError("intensity refinement: the displacement field needs at least 2 voxels per axis");
  if (!in.intraop_t1.grid.same_geometry(g) || in.intraop_t1.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the intraop image is not on the field's grid");
  if (!in.intraop_labels.grid.same_geometry(g) || in.intraop_labels.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the intraop labels are not on the field's grid");
  if (!in.brain_sdf_mm.grid.same_geometry(g) || in.brain_sdf_mm.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the brain distance map is not on the field's grid");
  if (in.preop_t1.grid.voxel_count() == 0 || in.preop_t1.voxels.size() != in.preop_t1.grid.voxel_count())
    throw InputError("intensity refinement: the preop image is empty");
  if (in.preop_t1_at_resolution && !in.preop_t1_at_resolution->grid.same_geometry(in.preop_t1.grid))
    throw InputError("intensity refinement: the blurred preop is not on the preop's grid");
}

}  // namespace

// The preop T1 as the intraop scanner would record it: each intraop voxel
// integrates a box of one pixel in-plane (variance h^2 / 12) and a slice
// profile across, taken as a Gaussian of FWHM one slice (a 2D
// acquisition's; the slice axis is the coarsest one), of which the preop
// voxel's own box (p^2 / 12) is already in the preop. Without it a sharp
// 1 mm preop is compared with a 2.4 mm slice's partial-volume average. The
// covariance is read on the preop's axes (its diagonal; exact for aligned
// grids).
Eigen::Vector3d preop_point_spread_sigma_voxels(const Grid3& preop, const Grid3& intraop) {
  const Eigen::Vector3d h = intraop.spacing_mm(), pre = preop.spacing_mm();
  int slice = 2;
  for (int a = 0; a < 3; ++a)
    if (h[a] > h[slice] * (1 + 1e-6)) slice = a;
  Eigen::Vector3d variance = h.cwiseProduct(h) / 12.0;
  variance[slice] = std::pow(h[slice] / 2.3548, 2);
  Eigen::Matrix3d r_in = intraop.world_from_voxel.topLeftCorner<3, 3>(), r_pre = preop.world_from_voxel.topLeftCorner<3, 3>();
  for (int a = 0; a < 3; ++a) r_in.col(a).normalize(), r_pre.col(a).normalize();
  const Eigen::Matrix3d on_preop_axes = r_pre.transpose() * r_in * variance.asDiagonal() * r_in.transpose() * r_pre;
  Eigen::Vector3d sigma_voxels;
  for (int a = 0; a < 3; ++a)
    sigma_voxels[a] = std::sqrt(std::max(0.0, on_preop_axes(a, a) - pre[a] * pre[a] / 12.0)) / pre[a];
  return sigma_voxels;
}

ImageF preop_at_intraop_resolution(const ImageF& preop, const Grid3& intraop) {
  ImageF out = preop;
  gaussian_smooth_voxels(out, preop_point_spread_sigma_voxels(preop.grid, intraop));
  return out;
}

namespace {

double median_intensity(const std::vector<Sample>& s) {
  std::vector<double> v;
  v.reserve(s.size());
  for (const Sample& x : s) v.push_back(x.intensity);
  return median(std::move(v));
}

}  // namespace

std::string validation_error(const IntensityRefinementParameters& p) {
  if (!(p.lattice_spacing_mm >= 2 && p.lattice_spacing_mm <= 50)) return "lattice_spacing_mm must be in [2, 50]";
  if (p.iterations < 1 || p.iterations > 100) return "iterations must be in 1..100";
  if (!(p.convergence_mm > 0)) return "convergence_mm must be > 0";
  if (!(p.membrane_weight >= 0 && std::isfinite(p.membrane_weight))) return "membrane_weight must be >= 0";
  if (!(p.shrink_weight_per_mm2 > 0 && std::isfinite(p.shrink_weight_per_mm2)))
    return "shrink_weight_per_mm2 must be > 0 (without it a region without image edges is undetermined)";
  if (!(p.smoothing_length_mm >= 0 && p.smoothing_length_mm <= 50)) return "smoothing_length_mm must be in [0, 50]";
  if (!(p.fem_trust_length_mm > 0 && p.fem_trust_length_mm <= 1000))
    return "fem_trust_length_mm must be in (0, 1000] (without it a region without image edges is undetermined)";
  if (!(p.max_correction_mm > 0 && p.max_correction_mm <= 20)) return "max_correction_mm must be in (0, 20]";
  if (!(p.max_step_mm > 0)) return "max_step_mm must be > 0";
  if (!(p.sample_spacing_mm > 0)) return "sample_spacing_mm must be > 0";
  if (p.max_samples < 1000) return "max_samples must be >= 1000";
  if (!(p.boundary_margin_mm >= 0)) return "boundary_margin_mm must be >= 0";
  if (!(p.robust_scale > 0)) return "robust_scale must be > 0";
  if (p.bias_degree < 0 || p.bias_degree > 3) return "bias_degree must be in 0..3";
  if (!(p.outside_fade_mm >= 0)) return "outside_fade_mm must be >= 0";
  if (!(p.min_explained_variance >= 0 && p.min_explained_variance < 1)) return "min_explained_variance must be in [0, 1)";
  return "";
}

void validate(const IntensityRefinementParameters& p) {
  const std::string error = validation_error(p);
  if (!error.empty()) throw InputError("intensity refinement: " + error);
}

void to_json(nlohmann::json& j, const IntensityRefinementReport& r) {
  if (!r.applied) {
    j = {{"applied", false}, {"skipped", r.skipped_reason}};
    if (r.explained_variance != 0) j["explained_variance"] = r.explained_variance;
    return;
  }
  j = {{"applied", true},
       {"iterations", r.iterations},
       {"candidates", r.candidates},
       {"samples", r.samples},
       {"bias_samples", r.bias_samples},
       {"rms_residual_before", r.rms_residual_before},
       {"rms_residual_after", r.rms_residual_after},
       {"max_correction_mm", r.max_correction_mm},
       {"mean_correction_mm", r.mean_correction_mm},
       {"bias_model", r.bias_model},
       {"explained_variance", r.explained_variance},
       {"data_curvature_per_mm2", r.data_curvature_per_mm2},
       {"smoothing_length_mm", r.smoothing_length_mm},
       {"seconds", {{"sampling", r.sampling_seconds}, {"optimise", r.optimise_seconds}, {"apply", r.apply_seconds},
                    {"total", r.seconds}}}};
}

IntensityRefinementReport refine_with_intensity(VectorImage3& pullback_mm, const IntensityRefinementInput& input,
                                                const IntensityRefinementParameters& p) {
  Stopwatch clock;
  validate(p);
  check_inputs(pullback_mm, input);
  IntensityRefinementReport report;
  const Boxes boxes = find_boxes(input.brain_sdf_mm, input.intraop_labels, input.background_label, p.outside_fade_mm);
  if (boxes.region.empty) {
    report.skipped_reason = "no brain region in the intraop labels";
    return report;
  }
  Lattice lattice(boxes.region, pullback_mm.grid, p.lattice_spacing_mm);
  const bool blur_here = p.match_point_spread && !input.preop_t1_at_resolution;
  const ImageF blurred = blur_here ? preop_at_intraop_resolution(input.preop_t1, pullback_mm.grid) : ImageF();
  const LinearSampler preop(!p.match_point_spread ? input.preop_t1
                            : blur_here           ? blurred
                                                  : *input.preop_t1_at_resolution);
  Samples samples = prepare_samples(pullback_mm, input, p, lattice, preop, boxes);
  report.candidates = samples.candidates;
  report.samples = samples.motion.size();
  report.bias_samples = samples.bias.size();
  if (samples.motion.size() < 1000) {
    report.skipped_reason = "too few tissue samples away from the boundary (" + std::to_string(report.samples) + ")";
    return report;
  }
  report.sampling_seconds = clock.seconds();
  const double median = std::max(median_intensity(samples.bias), 1e-12);
  report.iterations = optimise(lattice, samples.motion, samples.bias, preop, p, samples.density_per_mm3,
                               pullback_mm.grid.spacing_mm().maxCoeff(), 1e-3 * median, &report);
  if (!report.skipped_reason.empty()) return report;
  report.optimise_seconds = clock.seconds() - report.sampling_seconds;
  report.rms_residual_before /= median;
  report.rms_residual_after /= median;
  const CorrectionStats st = apply_correction(pullback_mm, lattice, input.brain_sdf_mm, boxes.region, p.outside_fade_mm);
  report.applied = true;
  report.max_correction_mm = st.max_mm;
  report.mean_correction_mm = st.voxels ? st.sum_mm / static_cast<double>(st.voxels) : 0.0;
  report.seconds = clock.seconds();
  report.apply_seconds = report.seconds - report.sampling_seconds - report.optimise_seconds;
  return report;
}

}  // namespace brainshift
