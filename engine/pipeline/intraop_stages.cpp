// The per-scan stages. Everything here runs while the surgeon waits: the
// budget is about a second, so no stage re-does preop work.
#include <algorithm>
#include <cmath>
#include <future>
#include <optional>

#include "core/errors.h"
#include "core/timer.h"
#include "field/displacement_field.h"
#include "field/metrics.h"
#include "field/unfold.h"
#include "field/warp.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "image/resample.h"
#include "pipeline/plausibility_stage.h"
#include "pipeline/resection_stage.h"
#include "pipeline/surface_stage.h"
#include "pipeline/warm_state.h"
#include "registration/affine_registration.h"
#include "protocol/stage_names.h"
#include "registration/intensity_refinement.h"

namespace brainshift {
namespace stages = protocol::stages;
namespace {

struct StageClock {
  const ProgressFn& progress;
  nlohmann::json& timings;
  Stopwatch watch;
  double nested_seconds = 0;
  // Stage names from protocol/stage_names.h, the one vocabulary.
  void start(std::string_view stage) {
    watch.lap();
    nested_seconds = 0;
    if (progress) progress(std::string(stage), 0.0, 0.0);
  }
  double done(std::string_view stage) {
    const double s = watch.lap() - nested_seconds;
    timings[std::string(stage)] = s;
    if (progress) progress(std::string(stage), 1.0, s);
    return s;
  }
  // A stage run inside another one ("refine" between the field and its
  // Jacobian check): reported under its own name and not counted twice, so
  // the stages still add up to "total".
  template <class Fn>
  void nested(std::string_view stage, Fn&& fn) {
    if (progress) progress(std::string(stage), 0.0, 0.0);
    Stopwatch w;
    fn();
    const double s = w.seconds();
    timings[std::string(stage)] = s;
    nested_seconds += s;
    if (progress) progress(std::string(stage), 1.0, s);
  }
};

// The intraop T1 corrects the interior of the non-rigid field
// (registration/intensity_refinement.h), before the Jacobian gate sees it.
nlohmann::json refine_interior(VectorImage3& field, WarmState& warm, const IntraopInput& input,
                               const IntraopDistanceMaps& maps, const PipelineParameters& params,
                               const std::string& failure) {
  const auto skipped = [](const char* why) { return nlohmann::json{{"applied", false}, {"skipped", why}}; };
  if (!params.intensity.enabled) return skipped("disabled");
  if (!input.t1) return skipped("no intraop image");
  if (!failure.empty()) return skipped("no non-rigid field to refine");
  std::vector<std::uint16_t> tissue;
  for (const auto& e : params.label_table.entries)
    if (e.role != LabelRole::cavity) tissue.push_back(e.value);
  IntensityRefinementInput in{*input.t1, input.labels, maps.outer_sdf_mm, warm.preop.t1, tissue, 0};
  if (params.intensity.match_point_spread) in.preop_t1_at_resolution = &preop_t1_at_resolution(warm, field.grid);
  return refine_with_intensity(field, in, params.intensity);
}

// Union of two masks' bounding boxes, grown by margin_mm.
VoxelBox joint_box(const Mask& a, const Mask& b, double margin_mm) {
  VoxelBox ba = bounding_box_voxels(a), bb = bounding_box_voxels(b);
  if (ba.empty) ba = bb;
  if (bb.empty) bb = ba;
  VoxelBox out = ba;
  for (int d = 0; d < 3; ++d) {
    out.lo[d] = std::min(ba.lo[d], bb.lo[d]);
    out.hi[d] = std::max(ba.hi[d], bb.hi[d]);
  }
  return grow_box(out, a.grid, margin_mm);
}

nlohmann::json label_metrics(const LabelImage& warped, const LabelImage& intraop, const LabelTable& table) {
  nlohmann::json out;
  for (const auto& e : table.entries) {
    const Mask a = mask_of_labels(warped, {e.value});
    const Mask b = mask_of_labels(intraop, {e.value});
    if (count_nonzero(b) == 0) continue;  // only structures the intraop segmentation has
    const VoxelBox box = joint_box(a, b, 5.0);
    const SurfaceDistance d = surface_distance(crop_to_box(a, box), crop_to_box(b, box));
    const double dice = dice_per_label(warped, intraop, {e.value}).front().dice;
    out[e.name] = {{"dice", dice}, {"mean_surface_distance_mm", d.mean_mm}, {"hausdorff95_mm", d.hd95_mm}};
  }
  return out;
}

// When a resectable structure was removed, solves again in the system where
// its wall is fixed too (resection_stage.h). The second solve failing leaves
// the first result standing: it is valid, only blind to the cavity.
void solve_with_resection(WarmState& warm, const IntraopInput& input, const Mask& brain_region,
                          const Eigen::Matrix4d& A, const std::vector<Eigen::Vector3d>& fixed_values,
                          const PipelineParameters& params, MeshDeformation& deformation, nlohmann::json& metrics) {
  if (warm.resectables.empty()) return;
  ResectionMatch resection =
      match_resection(warm, input, brain_region, A, deformation.nonrigid_mm, fixed_values, params);
  if (resection.system > 0) {
    std::vector<Eigen::Vector3d> nonrigid;
    try {
      warm.fem.drive_solve(resection.fixed_values_mm, nonrigid, resection.system);
      deformation.nonrigid_mm = std::move(nonrigid);
      resection.metrics["system"] = resection.system;
    } catch (const ComputeError& e) {
      resection.metrics["error"] = std::string("second solve failed, cavity ignored: ") + e.what();
    }
  }
  metrics["resection"] = std::move(resection.metrics);
}

// The answer's parameters with the prior-only pass's shortcuts
// (PassShortcuts): fewer membrane iterations per stiffness level.
PipelineParameters prior_pass_parameters(const PipelineParameters& params) {
  PipelineParameters p = params;
  const int iterations = params.auto_segmentation.passes.prior_surface_max_iterations;
  if (iterations > 0) {
    p.outer_surface.max_iterations = std::min(p.outer_surface.max_iterations, iterations);
    p.ventricle_surface.max_iterations = std::min(p.ventricle_surface.max_iterations, iterations);
  }
  return p;
}

}  // namespace

ScanResult run_intraop(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                       const ProgressFn& progress, bool with_quality_metrics, const std::string& forced_fallback,
                       const PassOptions& pass) {
  const LabelTable& table = params.label_table;
  Stopwatch total;
  ScanResult result;
  nlohmann::json timings;
  nlohmann::json metrics;
  StageClock clock{progress, timings, {}};

  clock.start(stages::kRead);
  validate_intraop_input(input, table);
  const auto cavities = table.cavity_labels();
  const std::uint16_t ventricle = cavities.empty() ? 0 : cavities.front();
  // The brain region of the intraop scan (all labels, enclosed holes filled),
  // computed once: field-of-view check, affine/surface targets, Jacobian region.
  const Mask brain_region = outline_mask(input.labels);
  const double intraop_volume_ml = volume_ml(brain_region);
  if (intraop_volume_ml < params.gates.min_intraop_brain_fraction * warm.brain_volume_ml)
    throw InputError("intraop labels: the brain covers only " + std::to_string(intraop_volume_ml) +
                     " ml against " + std::to_string(warm.brain_volume_ml) +
                     " ml preop; the field of view misses most of the brain");
  clock.done(stages::kRead);
  // Reading or decoding the images (the caller's) is part of what the surgeon waits for.
  timings[std::string(stages::kRead)] = timings[std::string(stages::kRead)].get<double>() + input.read_seconds;

  clock.start(stages::kAffine);
  const IntraopDistanceMaps maps = prepare_intraop_maps(input.labels, brain_region, table.brain_label(), ventricle);
  const AffineRegistrationResult affine = register_affine(warm.affine_samples, maps, params.affine, pass.affine_start,
                                                          pass.affine_start ? nullptr : pass.affine_candidate);
  const Eigen::Matrix4d A = affine.intraop_from_preop;
  result.intraop_from_preop = A;
  metrics["affine"] = {{"converged", affine.converged}, {"plausible", affine.plausible}, {"iterations", affine.iterations},
                       {"rms_surface_distance_mm", affine.rms_surface_distance_mm},
                       {"inlier_fraction", affine.inlier_fraction}, {"tolerance_met", affine.tolerance_met}, {"affine_kept", affine.affine_kept},
                       {"residual_sigma_mm", affine.residual_sigma_mm}, {"robust_scale_mm", affine.robust_scale_mm},
                       {"warm_start", pass.affine_start != nullptr}, {"message", affine.message}};
  clock.done(stages::kAffine);

  std::string failure = forced_fallback;
  if (failure.empty() && !affine.converged) failure = "affine registration did not converge: " + affine.message;
  // Is the input possible for this patient, and the affine a head moving?
  // Checked (and reported) even when the affine already failed: the report
  // then says what else is wrong with the input.
  PlausibilityReport plausibility;
  const std::string implausible = check_input_plausibility(warm, input, brain_region, A, params, plausibility);
  // The labels refused for their own geometry: the affine fitted to them
  // carries their error (a head does not shrink or swell), so the fallback
  // is its rigid part about the preop brain's centre (quality/
  // plausibility_gates.h); so too when the automatic segmentation's own
  // volume gate refused it before the stages (PassOptions::
  // forced_fallback_rigid). A caller that refused labels with their image
  // hands in the transform to deliver (PassOptions::forced_fallback_transform).
  // An affine that did not converge (an implausible determinant, or a fit
  // that explains too little of the labels) is never delivered itself: a
  // brain segmented in part gave one that shrank the preop five-fold, 40 mm
  // off at the landmarks (docs/PERFORMANCE.md 12.43). A head does not change
  // size: its rigid part, as for a refused geometry.
  const bool forced = !forced_fallback.empty();
  const bool affine_failed = !forced && !affine.converged;
  const bool geometry_refused =
      affine_failed || (failure.empty() && !implausible.empty() && refuses_labels_geometry(plausibility));
  std::optional<FallbackTransform> fallback_transform;
  if (forced && pass.forced_fallback_transform)
    fallback_transform = pass.forced_fallback_transform;
  else if ((forced && pass.forced_fallback_rigid) || geometry_refused)
    fallback_transform = FallbackTransform{
        rigid_part(A, warm.affine_samples.outer_moments.centroid_mm),
        forced          ? "rigid part of the affine (the automatic segmentation's brain volume was refused)"
        : affine_failed ? "rigid part of the affine (the affine did not converge)"
                        : "rigid part of the affine (the labels' geometry was refused)"};
  if (failure.empty()) failure = implausible;
  const Eigen::Matrix4d delivered_A = fallback_transform ? fallback_transform->intraop_from_preop : A;
  if (fallback_transform) {
    result.intraop_from_preop = delivered_A;
    metrics["affine"]["fallback_transform"] = fallback_transform->what;
    nlohmann::json rows = nlohmann::json::array();
    for (int r = 0; r < 4; ++r) rows.push_back({A(r, 0), A(r, 1), A(r, 2), A(r, 3)});
    metrics["affine"]["refused_intraop_from_preop"] = rows;
  }

  clock.start(stages::kSurface);
  std::vector<Eigen::Vector3d> fixed_values;
  std::optional<PipelineParameters> prior_params;
  if (pass.prior_only) prior_params = prior_pass_parameters(params);
  if (failure.empty())
    fixed_values = match_surfaces(warm, maps, A, input, prior_params ? *prior_params : params, metrics, &failure);
  clock.done(stages::kSurface);

  clock.start(stages::kSolve);
  MeshDeformation deformation;
  deformation.intraop_from_preop = delivered_A;
  deformation.nonrigid_mm.assign(warm.fem.mesh().node_count(), Eigen::Vector3d::Zero());
  if (failure.empty()) {
    try {
      const SolveReport solve = warm.fem.drive_solve(fixed_values, deformation.nonrigid_mm);
      metrics["solve"] = {{"iterations", solve.iterations}, {"relative_residual", solve.relative_residual},
                          {"solver", solve.solver_description}};
      failure = field_beyond_data(deformation.nonrigid_mm, fixed_values, params.gates, metrics["solve"]);
      if (failure.empty()) solve_with_resection(warm, input, brain_region, A, fixed_values, params, deformation, metrics);
      if (failure.empty()) failure = check_field_plausibility(warm, deformation.nonrigid_mm, params, plausibility);
      if (!failure.empty()) deformation.nonrigid_mm.assign(warm.fem.mesh().node_count(), Eigen::Vector3d::Zero());
    } catch (const ComputeError& e) {
      failure = e.what();
      deformation.nonrigid_mm.assign(warm.fem.mesh().node_count(), Eigen::Vector3d::Zero());
    }
  }
  clock.done(stages::kSolve);

  clock.start(stages::kField);
  FieldStats field_stats;
  Mask mesh_region;
  // The delivered field must not pull the preop brain into the gap a sinking
  // left (field/tissue_guard.h).
  if (!warm.preop_tissue_voxels) warm.preop_tissue_voxels = tissue_voxel_box(warm.preop.labels);
  // Given labels' outline is uncertain by a voxel of partial volume along the
  // grid's coarsest axis and the segmenter's millimetre (a hand or another
  // tool's segmentation: its partial-volume voxels were decided by someone
  // else's rule). The engine's own
  // segmentation is judged to its outline: measured on the hospital suite
  // and family 8, image only, the tolerance cost 0.003-0.004 mm of mean TRE
  // and left more of the gap drawn (docs/PERFORMANCE.md 12.32).
  const double outline_tolerance_mm =
      pass.segmented_by_engine ? 0.0 : input.labels.grid.spacing_mm().maxCoeff() + 1.0;
  const TissueGuard guard{&warm.preop.labels, *warm.preop_tissue_voxels, &brain_region, outline_tolerance_mm};
  result.pullback_field_mm = pullback_field(warm.fem.mesh(), deformation, input.labels.grid, params.field,
                                            &field_stats, &mesh_region, pass.guard_tissue ? &guard : nullptr);
  metrics["field_beyond_brain"] = {{"guarded", pass.guard_tissue},
                                   {"tissue_landing_voxels", field_stats.guard_landing_voxels},
                                   {"raised_voxels", field_stats.guard_raised_voxels},
                                   {"unresolved_voxels", field_stats.guard_unresolved_voxels}};
  // The fold gate judges the elastic solution's map of the brain: the intraop
  // outline where the deformed mesh covers it. Outline voxels beyond the mesh
  // (an outline a few mm above the matched surface) carry the field's fade to
  // the affine, an extension that folds under a large remainder whatever the
  // solution (docs/DESIGN.md "The fold gate judges the mesh's image").
  Mask fold_region = brain_region;
  std::size_t outline_beyond_mesh = 0;
  for (std::size_t v = 0; v < fold_region.voxels.size(); ++v)
    if (fold_region.voxels[v] && !mesh_region.voxels[v]) {
      fold_region.voxels[v] = 0;
      ++outline_beyond_mesh;
    }
  if (pass.prior_only && !params.auto_segmentation.passes.prior_refine)
    metrics["refine"] = {{"applied", false}, {"skipped", "a pass for the re-match's prior"}};
  else
    clock.nested(stages::kRefine, [&] {
      metrics["refine"] = refine_interior(result.pullback_field_mm, warm, input, maps, params, failure);
    });
  if (failure.empty()) {
    failure = check_image_plausibility(warm, input, brain_region, result.pullback_field_mm, A, params, plausibility);
    if (!failure.empty()) {
      deformation.nonrigid_mm.assign(warm.fem.mesh().node_count(), Eigen::Vector3d::Zero());
      result.pullback_field_mm = pullback_field(warm.fem.mesh(), deformation, input.labels.grid, params.field, &field_stats);
    }
  }
  metrics["plausibility"] = plausibility.to_json();
  JacobianStats jac = jacobian_stats(result.pullback_field_mm, &fold_region);
  if (failure.empty() && jac.min_det <= params.gates.min_jacobian_determinant) {
    // A few folded voxels (strongly compressed elements under a deep sinking)
    // are repaired locally before the whole non-rigid result is refused.
    UnfoldStats unfold;
    const bool repaired = unfold_field(result.pullback_field_mm, fold_region, params.unfold, &unfold);
    metrics["unfold"] = {{"folded_voxels_before", jac.folded_voxels}, {"repaired", repaired},
                         {"changed_voxels", unfold.changed_voxels}, {"rounds", unfold.rounds},
                         {"max_change_mm", unfold.max_change_mm}};
    jac = jacobian_stats(result.pullback_field_mm, &fold_region);
  }
  if (failure.empty() && jac.min_det <= params.gates.min_jacobian_determinant) {
    failure = "the non-rigid field folds (min Jacobian determinant " + std::to_string(jac.min_det) + ")";
    deformation.nonrigid_mm.assign(warm.fem.mesh().node_count(), Eigen::Vector3d::Zero());
    result.pullback_field_mm = pullback_field(warm.fem.mesh(), deformation, input.labels.grid, params.field, &field_stats);
    jac = jacobian_stats(result.pullback_field_mm, &fold_region);
  }
  // The whole outline as delivered, shell beyond the mesh included: not a
  // gate (above), but shown, so that a fold in the fade is never hidden.
  const JacobianStats outline_jac = jacobian_stats(result.pullback_field_mm, &brain_region);
  metrics["jacobian"] = {{"min", jac.min_det}, {"max", jac.max_det},
                         {"folded_voxels", jac.folded_voxels}, {"outline_voxels_beyond_mesh", outline_beyond_mesh},
                         {"outline_min", outline_jac.min_det}, {"outline_folded_voxels", outline_jac.folded_voxels}};
  clock.done(stages::kField);

  clock.start(stages::kWarp);
  // Each warp splits its slices over both cores (field/warp.h).
  result.warped_labels = warp_labels_nearest(warm.preop.labels, result.pullback_field_mm);
  if (!pass.prior_only) result.warped_t1 = warp_image_linear(warm.preop.t1, result.pullback_field_mm);
  clock.done(stages::kWarp);

  result.nonrigid_node_mm = deformation.nonrigid_mm;
  clock.start(stages::kModels);
  if (!pass.prior_only)
    for (const auto& [name, model] : warm.models)
      result.models[name] = carry(model.surface, model.binding, deformation);
  clock.done(stages::kModels);

  // "total" is the registration itself: the stages the issue lists (read,
  // affine, surface, solve, field, warp, models) and "refine" (timed inside
  // "field", counted once). The quality metrics are timed on their own as
  // "metrics" (about 0.3 s) and reported next to it, never hidden; the daemon
  // computes them just after announcing the field.
  timings[std::string(stages::kTotal)] = total.seconds() + input.read_seconds;
  if (!failure.empty()) {
    result.kind = ResultKind::affine_only_fallback;
    result.fallback_reason = failure;
  }
  metrics["result"] = std::string(protocol::to_string(result.kind));
  if (pass.prior_only) metrics["pass"] = "prior only: no warped T1, no models";
  if (!failure.empty()) metrics["fallback_reason"] = failure;
  result.metrics = std::move(metrics);
  result.timings = {{"intraop", timings},
                    {"preop", warm.timings},
                    {"mesh", {{"nodes", warm.fem.mesh().node_count()}, {"tets", warm.fem.mesh().tet_count()}}}};
  if (with_quality_metrics) add_quality_metrics(warm, input, params, result, progress);
  return result;
}

void complete_prior_pass(const WarmState& warm, ScanResult& result, const ProgressFn& progress) {
  nlohmann::json& timings = result.timings["intraop"];
  Stopwatch watch;
  if (progress) progress(std::string(stages::kWarp), 0.0, 0.0);
  result.warped_t1 = warp_image_linear(warm.preop.t1, result.pullback_field_mm);
  const double warp_s = watch.lap();
  if (progress) progress(std::string(stages::kWarp), 1.0, warp_s);
  if (progress) progress(std::string(stages::kModels), 0.0, 0.0);
  const MeshDeformation deformation{result.intraop_from_preop, result.nonrigid_node_mm};
  for (const auto& [name, model] : warm.models) result.models[name] = carry(model.surface, model.binding, deformation);
  const double models_s = watch.lap();
  if (progress) progress(std::string(stages::kModels), 1.0, models_s);
  const auto add = [&](std::string_view key, double s) {
    timings[std::string(key)] = timings.value(std::string(key), 0.0) + s;
  };
  add(stages::kWarp, warp_s);
  add(stages::kModels, models_s);
  add(stages::kTotal, warp_s + models_s);
  result.metrics.erase("pass");
}

// Dice and surface distances of the warped preop labels against the intraop
// labels, after the non-rigid step and through the affine alone, and the
// affine-only warped T1 the report compares against. The three pieces are
// independent and run side by side.
void add_quality_metrics(const WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                         ScanResult& result, const ProgressFn& progress) {
  const LabelTable& table = params.label_table;
  nlohmann::json& timings = result.timings["intraop"];
  StageClock clock{progress, timings, {}};
  clock.start(stages::kQualityMetrics);
  const Eigen::Matrix4d preop_from_intraop = result.intraop_from_preop.inverse();
  auto affine_only = std::async(std::launch::async, [&] {
    const LabelImage affine_labels = resample_nearest(warm.preop.labels, input.labels.grid, preop_from_intraop);
    return label_metrics(affine_labels, input.labels, table);
  });
  auto affine_t1 = std::async(std::launch::async, [&] {
    return resample_linear(warm.preop.t1, input.labels.grid, preop_from_intraop);
  });
  result.metrics["labels"] = label_metrics(result.warped_labels, input.labels, table);
  // A field worked on a coarser grid (the working or the stage grid) was
  // judged there by the fold gate; the field delivered, carried to the
  // scan's grid, is measured here too, over the scan's outline.
  if (result.metrics.contains("working_grid") || result.metrics.contains("stage_grid")) {
    const Mask outline = outline_mask(input.labels);
    const JacobianStats delivered = jacobian_stats(result.pullback_field_mm, &outline);
    result.metrics["jacobian"]["delivered_min"] = delivered.min_det;
    result.metrics["jacobian"]["delivered_folded_voxels"] = delivered.folded_voxels;
  }
  result.metrics["labels_affine_only"] = affine_only.get();
  result.warped_t1_affine_only = affine_t1.get();
  clock.done(stages::kQualityMetrics);
}

}  // namespace brainshift
