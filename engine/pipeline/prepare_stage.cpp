#include "pipeline/prepare_stage.h"
#include "pipeline/working_grid.h"
#include "protocol/stage_names.h"

#include <algorithm>
#include <cmath>
#include <future>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "image/image_stats.h"
#include "image/resample.h"
#include "registration/affine_registration.h"
#include "segmentation/head_mask.h"
#include "segmentation/label_image_check.h"
#include "segmentation/tissue_prior.h"

namespace brainshift {
namespace stages = protocol::stages;
namespace {

// Head outlines as label maps (1 = head) for the label affine; no ventricle
// term (value 2 is absent).
LabelImage as_labels(const Mask& m) {
  LabelImage out(m.grid, 0);
  for (std::size_t v = 0; v < m.voxels.size(); ++v) out.voxels[v] = m.voxels[v] ? 1 : 0;
  return out;
}

// The preop head as far as the intraop image can see it through a placement
// (intraop_from_preop): the part of the preop head mapped inside the intraop
// grid, and its outline points there. An intraop field of view cuts the head
// (the neck, the vertex); matched against the whole preop head, the moments
// and the outline would pull the placement toward shrinking it.
// Without a placement (nullptr) all of it.
PreopBoundarySamples visible_head(const Mask& head, const Grid3& intraop, const Eigen::Matrix4d* intraop_from_preop) {
  const Eigen::Matrix4d voxel_from_preop =
      intraop.voxel_from_world() * (intraop_from_preop ? *intraop_from_preop : Eigen::Matrix4d::Identity());
  auto visible = [&](const Eigen::Vector3d& p) {
    if (!intraop_from_preop) return true;
    const Eigen::Vector3d v = (voxel_from_preop * p.homogeneous()).head<3>();
    for (int a = 0; a < 3; ++a)
      if (v[a] < -0.5 || v[a] > intraop.dims[a] - 0.5) return false;
    return true;
  };
  Mask seen(head.grid, 0);
  for (int k = 0; k < head.grid.dims[2]; ++k)
    for (int j = 0; j < head.grid.dims[1]; ++j)
      for (int i = 0; i < head.grid.dims[0]; ++i)
        seen.at(i, j, k) = head.at(i, j, k) && visible(head.grid.world_mm(i, j, k));
  PreopBoundarySamples samples;
  samples.outer_moments = mask_moments(seen);
  for (const auto& p : mask_boundary_points_mm(head))
    if (visible(p)) samples.outer_mm.push_back(p);
  return samples;
}

// Two passes: the preop head seen through the identity (scanners place a
// patient's head within centimetres of the same RAS position) or, when that
// sees too little of it, the whole head; then seen through the first result.
Eigen::Matrix4d place_preop_by_head(WarmState& warm, const ImageF& image, const AffineRegistrationParameters& affine,
                                    nlohmann::json& metrics) {
  if (!warm.preop_head) {
    warm.preop_head = segmentation::head_mask(warm.preop.t1);
    if (count_nonzero(*warm.preop_head) == 0) throw ComputeError("the preop image shows no head (flat image)");
  }
  const Mask head = segmentation::head_mask(image);
  if (count_nonzero(head) == 0) throw InputError("intraop image: no head found (the image is flat)");
  const IntraopDistanceMaps maps = prepare_intraop_maps(as_labels(head), 1, 2);
  AffineRegistrationParameters p = affine;
  p.ventricle_weight = 0;
  Eigen::Matrix4d placement = Eigen::Matrix4d::Identity();
  AffineRegistrationResult r;
  for (int pass = 0; pass < 2; ++pass) {
    PreopBoundarySamples samples = visible_head(*warm.preop_head, image.grid, &placement);
    if (pass == 0 && samples.outer_moments.volume_ml < 0.5 * volume_ml(head))
      samples = visible_head(*warm.preop_head, image.grid, nullptr);
    if (samples.outer_mm.size() < 100) break;
    r = register_affine(samples, maps, p);
    placement = r.intraop_from_preop;
  }
  metrics = {{"converged", r.converged}, {"rms_surface_distance_mm", r.rms_surface_distance_mm},
             {"inlier_fraction", r.inlier_fraction}, {"message", r.message}};
  return placement;
}

std::vector<std::uint16_t> ventricle_labels(const LabelTable& table) { return table.cavity_labels(); }

// The preop where the head's placement puts it (segmentation::PreopSeen):
// its T1 and its own fluid and tissue intensities. Without ventricles in the
// preop labels there is no fluid to compare with: the medians are equal and
// the test is off.
segmentation::PreopSeen preop_as_seen(WarmState& warm, const LabelTable& table, const LabelImage& carried,
                                      const Eigen::Matrix4d& intraop_from_preop) {
  if (!warm.preop_fluid_tissue_medians) {
    const auto vent = ventricle_labels(table);
    std::vector<float> fluid, tissue;
    const auto& labels = warm.preop.labels.voxels;
    for (std::size_t v = 0; v < labels.size(); ++v) {
      if (std::find(vent.begin(), vent.end(), labels[v]) != vent.end()) fluid.push_back(warm.preop.t1.voxels[v]);
      else if (labels[v] == table.brain_label()) tissue.push_back(warm.preop.t1.voxels[v]);
    }
    const double f = median_in_place(fluid), t = median_in_place(tissue);
    warm.preop_fluid_tissue_medians = fluid.empty() || tissue.empty() ? std::array<double, 2>{0, 0} : std::array<double, 2>{f, t};
  }
  segmentation::PreopSeen seen;
  seen.image = &warm.preop.t1;
  seen.preop_from_intraop = intraop_from_preop.inverse();
  seen.fluid_median = (*warm.preop_fluid_tissue_medians)[0];
  seen.tissue_median = (*warm.preop_fluid_tissue_medians)[1];
  const auto resectable = table.resectable_labels();
  if (!resectable.empty()) seen.resectable = mask_of_labels(carried, resectable);
  return seen;
}

// The inner band one voxel inside the outline's surface.
Mask inner_surface_band(const Mask& outline) {
  const double h = outline.grid.spacing_mm().minCoeff();
  return boundary_voxels(erode(outline, 1.01 * h));
}

// What the gates measure of the preop carried by the head placement: the
// same for every round of a scan, so measured once.
struct CarriedPreopVolumes {
  double brain_ml = 0, resectable_ml = 0, ventricles_ml = 0;
};

CarriedPreopVolumes carried_preop_volumes(const LabelImage& carried_preop, const LabelTable& table) {
  // The carried preop is already on the intraop grid through the placement,
  // so its volume there includes the affine's scale and the field of view.
  CarriedPreopVolumes c;
  c.brain_ml = volume_ml(outline_mask(carried_preop));
  for (auto v : table.resectable_labels()) c.resectable_ml += volume_ml(mask_of_labels(carried_preop, {v}));
  c.ventricles_ml = volume_ml(mask_of_labels(carried_preop, ventricle_labels(table)));
  return c;
}

SegmentationGates check_against(const LabelImage& segmentation, const ImageF& confidence,
                                const CarriedPreopVolumes& preop, const LabelTable& table,
                                const AutoSegmentationParameters& params, double open_fluid_ml) {
  SegmentationGates g;
  const Mask outline = outline_mask(segmentation);
  const double resectable_ml = preop.resectable_ml;
  const double seg_ml = volume_ml(outline), preop_ml = preop.brain_ml;
  const double change = preop_ml > 0 ? seg_ml / preop_ml - 1 : -1;
  // Smaller by what may be resected, and by the fluid found in the gap a
  // sinking left (fluid by its intensity: a lost lobe is tissue).
  const double lowest =
      -params.max_brain_volume_change - (preop_ml > 0 ? (resectable_ml + open_fluid_ml) / preop_ml : 0);
  g.metrics["brain_volume"] = {{"segmented_ml", seg_ml}, {"preop_ml", preop_ml}, {"change", change},
                               {"open_fluid_ml", open_fluid_ml},
                               {"allowed", {lowest, params.max_brain_volume_change}}};
  if (change < lowest || change > params.max_brain_volume_change)
    g.failure = "automatic segmentation: the brain's volume differs from the preop's by " +
                std::to_string(100 * change) + " % (allowed " + std::to_string(100 * lowest) + " to +" +
                std::to_string(100 * params.max_brain_volume_change) + " %)";

  const auto vent = ventricle_labels(table);
  const double seg_vent = volume_ml(mask_of_labels(segmentation, vent));
  const double preop_vent = preop.ventricles_ml;
  const double fraction = preop_vent > 0 ? seg_vent / preop_vent : 1.0;
  g.metrics["ventricles"] = {{"segmented_ml", seg_vent}, {"preop_ml", preop_vent}, {"fraction", fraction},
                             {"min_fraction", params.min_ventricle_fraction}};
  if (g.failure.empty() && preop_vent > 0 && fraction < params.min_ventricle_fraction)
    g.failure = "automatic segmentation: no ventricles found (" + std::to_string(seg_vent) + " ml against " +
                std::to_string(preop_vent) + " ml preop)";

  const VoxelBox box = grow_box(bounding_box_voxels(outline), outline.grid, 3.0);
  std::size_t band_voxels = 0, uncertain = 0;
  if (!box.empty) {
    const Mask band = inner_surface_band(crop_to_box(outline, box));
    for (int k = 0; k < band.grid.dims[2]; ++k)
      for (int j = 0; j < band.grid.dims[1]; ++j)
        for (int i = 0; i < band.grid.dims[0]; ++i) {
          if (!band.at(i, j, k)) continue;
          ++band_voxels;
          uncertain += confidence.at(i + box.lo[0], j + box.lo[1], k + box.lo[2]) < params.min_surface_confidence;
        }
  }
  const double uncertain_fraction = band_voxels ? static_cast<double>(uncertain) / static_cast<double>(band_voxels) : 1.0;
  g.metrics["outer_surface"] = {{"uncertain_fraction", uncertain_fraction},
                                {"min_confidence", params.min_surface_confidence},
                                {"max_uncertain_fraction", params.max_uncertain_surface_fraction}};
  if (g.failure.empty() && uncertain_fraction > params.max_uncertain_surface_fraction)
    g.failure = "automatic segmentation: the outer brain surface is uncertain over " +
                std::to_string(100 * uncertain_fraction) + " % of its area (limit " +
                std::to_string(100 * params.max_uncertain_surface_fraction) + " %)";
  g.metrics["passed"] = g.failure.empty();
  return g;
}

}  // namespace

SegmentationGates check_segmentation(const LabelImage& segmentation, const ImageF& confidence,
                                     const LabelImage& carried_preop, const LabelTable& table,
                                     const AutoSegmentationParameters& params, double open_fluid_ml) {
  return check_against(segmentation, confidence, carried_preop_volumes(carried_preop, table), table, params,
                       open_fluid_ml);
}

namespace {

// The image-only scan on the image's own grid (see register_image_only).
ScanResult register_on_grid(WarmState& warm, const ImageF& image, double read_seconds, const PipelineParameters& params,
                            const ProgressFn& progress, bool with_quality_metrics) {
  const LabelTable& table = params.label_table;
  const AutoSegmentationParameters& ap = params.auto_segmentation;
  if (image.grid.voxel_count() == 0) throw InputError("intraop image: the image has no voxels");
  for (float v : image.voxels)
    if (!std::isfinite(v)) throw InputError("intraop image: contains non-finite values");

  Stopwatch watch, scan_watch;
  double segment_seconds = 0;
  nlohmann::json seg_metrics;
  if (progress) progress(std::string(stages::kSegment), 0.0, 0.0);
  const Eigen::Matrix4d placement = place_preop_by_head(warm, image, params.affine, seg_metrics["head_placement"]);
  LabelImage carried = resample_nearest(warm.preop.labels, image.grid, placement.inverse());
  const segmentation::PreopSeen seen = preop_as_seen(warm, table, carried, placement);
  auto segment = [&](const LabelImage& prior_labels, double width_mm, double ventricle_shift_mm, bool open_fluid_rule = true,
                     const segmentation::IntraopSegmentation* fitted = nullptr,
                     const Mask* gap_found_before = nullptr) {
    segmentation::SegmentationParameters sp = ap.classifier;
    if (!open_fluid_rule) sp.max_sulcus_half_width_mm = 0;
    // The classified box ends where the prior meets its floor (docs/DESIGN.md
    // "Automatic intraop segmentation", item 7).
    sp.margin_mm = segmentation::prior_reach_mm(width_mm, sp.prior_floor);
    sp.prior_width_mm = width_mm;
    sp.ventricle_prior_width_mm = ap.ventricle_prior_width_mm;
    sp.ventricle_shift_mm = ventricle_shift_mm;
    if (ventricle_shift_mm > 0) sp.prior_inward_width_mm = ap.prior_inward_width_affine_mm;
    sp.max_filled_hole_ml = params.min_resection_cavity_ml;
    return segmentation::segment_intraop(image, prior_labels, table.brain_label(), ventricle_labels(table), sp, fitted,
                                         gap_found_before, &seen);
  };
  // As for given labels (run_intraop), but said of the image and before the
  // segmentation's time is spent: the preop placed by the head shows how much
  // of the brain the field of view holds.
  const CarriedPreopVolumes carried_volumes = carried_preop_volumes(carried, table);
  if (carried_volumes.brain_ml < params.gates.min_intraop_brain_fraction * warm.brain_volume_ml)
    throw InputError("intraop image: the field of view holds " + std::to_string(carried_volumes.brain_ml) +
                     " ml of the preop's " + std::to_string(warm.brain_volume_ml) +
                     " ml brain (placed by the head); it misses most of the brain");
  segmentation::IntraopSegmentation seg = segment(carried, ap.prior_width_affine_mm, ap.ventricle_shift_affine_mm);
  if (!seg.refusal.empty()) throw InputError("intraop image: " + seg.refusal);
  SegmentationGates gates = check_against(seg.labels, seg.confidence, carried_volumes, table, ap, seg.open_fluid_ml);
  segment_seconds += watch.lap();
  if (progress) progress(std::string(stages::kSegment), 1.0, segment_seconds);

  // The gates are checked before the stages, not beside them: every stage
  // already splits its work over both cores (the affine in every iteration),
  // and a third thread slowed them by more than the check costs.
  // A pass a re-match follows only makes the re-match's prior: it runs light
  // (PassOptions::prior_only). A light pass the stages refuse is run again in
  // full when a shortcut changed its field, so that the shortcuts never
  // decide a refusal (nor its reason); a light pass that ends up the answer
  // (refused, or its re-match refused) is completed: by the outputs it
  // skipped when its field is a full pass's, else by the full pass.
  // A re-match's pass starts its affine from the pass before it (item 9).
  const bool light_field_is_full = ap.passes.prior_refine && ap.passes.prior_surface_max_iterations == 0;
  auto run_pass = [&](const segmentation::IntraopSegmentation& s, bool rematch_follows, bool& prior_only,
                      const Eigen::Matrix4d* affine_start = nullptr) {
    const IntraopInput input{s.labels, image, read_seconds, s.open_fluid_ml};
    if (!ap.passes.warm_start_affine) affine_start = nullptr;
    prior_only = false;
    if (rematch_follows) {
      ScanResult light = run_intraop(warm, input, params, progress, false, "", PassOptions{true, affine_start});
      prior_only = light.kind == ResultKind::nonrigid;
      if (prior_only) return light;
      if (light_field_is_full) {
        complete_prior_pass(warm, light, progress);
        return light;
      }
    }
    return run_intraop(warm, input, params, progress, false, "", PassOptions{false, affine_start});
  };
  bool result_prior_only = false;
  ScanResult result = gates.failure.empty()
                          ? run_pass(seg, ap.rematch_rounds > 0, result_prior_only)
                          : run_intraop(warm, IntraopInput{seg.labels, image, read_seconds, seg.open_fluid_ml}, params, progress, false,
                                        gates.failure);
  nlohmann::json rounds = nlohmann::json::array();
  rounds.push_back({{"prior_width_mm", seg.report["prior_width_mm"]}, {"gates", gates.metrics}});
  // The open-fluid rule reshapes the outline by shape, not by intensity
  // (docs/DESIGN.md "Automatic intraop segmentation", item 7); where the
  // stages refuse the field its outline gives (a fold: the cortex over a
  // resection cavity taken for the cap of a gap), the segmentation by the
  // image alone is tried once, and kept only if the stages accept it.
  bool open_fluid_rule = true;
  if (result.kind != ResultKind::nonrigid && gates.failure.empty() && seg.open_fluid_ml > 0) {
    watch.lap();
    auto plain = segment(carried, ap.prior_width_affine_mm, ap.ventricle_shift_affine_mm, false);
    SegmentationGates plain_gates = check_against(plain.labels, plain.confidence, carried_volumes, table, ap, 0.0);
    segment_seconds += watch.lap();
    rounds.push_back({{"prior_width_mm", plain.report["prior_width_mm"]}, {"gates", plain_gates.metrics},
                      {"open_fluid_rule", false}, {"refusal", plain.refusal}});
    if (plain.refusal.empty() && plain_gates.failure.empty()) {
      bool pass_prior_only = false;
      ScanResult pass = run_pass(plain, ap.rematch_rounds > 0, pass_prior_only);
      if (pass.kind == ResultKind::nonrigid) {
        rounds.front()["kept"] = false;
        rounds.front()["fallback_reason"] = result.fallback_reason;
        open_fluid_rule = false;
        seg = std::move(plain);
        gates = std::move(plain_gates);
        result = std::move(pass);
        result_prior_only = pass_prior_only;
      } else {
        rounds.back()["kept"] = false;
      }
    } else {
      rounds.back()["kept"] = false;
    }
  }
  for (int round = 1; round <= ap.rematch_rounds && result.kind == ResultKind::nonrigid; ++round) {
    // Re-match: the preop carried by the non-rigid estimate (the pass's own
    // warped labels), a narrower prior, a smaller box. The gap a sinking left
    // was found against the head's placement, as the gates measure: the
    // first round's finding stands for the next. rematch_reuses_fit: the
    // classes and bias fitted before are reused (off by default).
    watch.lap();
    auto next = segment(result.warped_labels, ap.prior_width_nonrigid_mm, 0.0, open_fluid_rule,
                        ap.rematch_reuses_fit ? &seg : nullptr,
                        ap.rematch_gaps_found_before ? &seg.open_fluid : nullptr);
    next.open_fluid_ml = std::max(seg.open_fluid_ml, next.open_fluid_ml);
    SegmentationGates next_gates =
        check_against(next.labels, next.confidence, carried_volumes, table, ap, next.open_fluid_ml);
    segment_seconds += watch.lap();
    if (!next.refusal.empty() || !next_gates.failure.empty()) {  // the previous pass stands
      rounds.push_back({{"prior_width_mm", next.report["prior_width_mm"]}, {"gates", next_gates.metrics},
                        {"refusal", next.refusal}, {"kept", false}});
      break;
    }
    bool pass_prior_only = false;
    ScanResult pass = run_pass(next, round < ap.rematch_rounds, pass_prior_only, &result.intraop_from_preop);
    if (pass.kind != ResultKind::nonrigid) {  // a re-match the stages refuse (a fold): the previous pass stands
      rounds.push_back({{"prior_width_mm", next.report["prior_width_mm"]}, {"gates", next_gates.metrics},
                        {"fallback_reason", pass.fallback_reason}, {"kept", false}});
      break;
    }
    seg = std::move(next);
    gates = std::move(next_gates);
    result = std::move(pass);
    result_prior_only = pass_prior_only;
    rounds.push_back({{"prior_width_mm", seg.report["prior_width_mm"]}, {"gates", gates.metrics}});
  }
  if (result_prior_only && light_field_is_full) {  // the answer: the outputs the light pass skipped
    complete_prior_pass(warm, result, progress);
  } else if (result_prior_only) {  // the answer: the full pass on the segmentation that stands
    const Eigen::Matrix4d same_labels_affine = result.intraop_from_preop;
    bool unused = false;
    result = run_pass(seg, false, unused, &same_labels_affine);
  }
  seg_metrics["classifier"] = seg.report;
  seg_metrics["gates"] = gates.metrics;
  seg_metrics["rounds"] = rounds;
  result.metrics["segmentation"] = seg_metrics;
  auto& t = result.timings["intraop"];
  t[std::string(stages::kSegment)] = segment_seconds;
  // Everything but the segmentation and the answer's own pass (whose total
  // includes the read) was an earlier pass.
  const double scan_seconds = scan_watch.seconds(), answer_pass_seconds = t.value("total", 0.0) - read_seconds;
  t["earlier_passes"] = std::max(0.0, scan_seconds - segment_seconds - answer_pass_seconds);
  t["total"] = scan_seconds + read_seconds;
  result.intraop_labels = std::move(seg.labels);
  result.segmentation_confidence = std::move(seg.confidence);
  if (with_quality_metrics)
    add_quality_metrics(warm, IntraopInput{*result.intraop_labels, image}, params, result, progress);
  return result;
}

}  // namespace

ScanResult register_image_only(WarmState& warm, const ImageF& image, double read_seconds, const PipelineParameters& params,
                               const ProgressFn& progress, bool with_quality_metrics) {
  if (image.grid.voxel_count() == 0) throw InputError("intraop image: the image has no voxels");
  const Grid3 work = working_grid(image.grid, params.auto_segmentation.working_spacing_mm);
  if (work.dims == image.grid.dims)
    return register_on_grid(warm, image, read_seconds, params, progress, with_quality_metrics);
  Stopwatch watch;
  for (float v : image.voxels)
    if (!std::isfinite(v)) throw InputError("intraop image: contains non-finite values");
  const ImageF coarser = downsample_linear(image, work);
  double own_seconds = watch.lap();
  ScanResult result = register_on_grid(warm, coarser, read_seconds, params, progress, false);
  watch.lap();
  carry_to_grid(warm, result, image.grid);
  own_seconds += watch.lap();
  const auto triple = [](const auto& v) { return nlohmann::json::array({v[0], v[1], v[2]}); };
  result.metrics["segmentation"]["working_grid"] = {
      {"dims", triple(work.dims)}, {"spacing_mm", triple(work.spacing_mm())},
      {"image_dims", triple(image.grid.dims)}, {"image_spacing_mm", triple(image.grid.spacing_mm())}};
  auto& t = result.timings["intraop"];
  t["working_grid"] = own_seconds;
  t[std::string(stages::kTotal)] = t.value(std::string(stages::kTotal), 0.0) + own_seconds;
  if (with_quality_metrics)
    add_quality_metrics(warm, IntraopInput{*result.intraop_labels, image}, params, result, progress);
  return result;
}

ScanResult register_labels_with_image(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                      const ProgressFn& progress, bool with_quality_metrics) {
  const LabelTable& table = params.label_table;
  validate_intraop_input(input, table);
  Stopwatch watch;
  double check_seconds = 0;
  auto check = std::async(std::launch::async, [&] {
    SerialOnThisThread beside_the_stages;
    Stopwatch w;
    segmentation::LabelImageCheckParameters p = params.auto_segmentation.label_image_check;
    p.classifier.max_filled_hole_ml = params.min_resection_cavity_ml;
    auto c = segmentation::check_labels_against_image(*input.t1, input.labels, table.brain_label(),
                                                      ventricle_labels(table), p);
    check_seconds = w.seconds();
    return c;
  });
  ScanResult result = run_intraop(warm, input, params, progress, false);
  segmentation::LabelImageCheck c = check.get();
  if (!c.failure.empty() && result.kind == ResultKind::nonrigid) {
    const nlohmann::json first_timings = result.timings["intraop"];
    result = run_intraop(warm, input, params, progress, false,
                         "the intraop labels disagree with the intraop image: " + c.failure);
    result.timings["intraop"]["earlier_passes"] = first_timings.value("total", 0.0);
  }
  // The answer waits for the check: the wait is part of what the surgeon waits for.
  result.timings["intraop"][std::string(stages::kTotal)] = watch.seconds() + input.read_seconds;
  c.metrics["seconds"] = check_seconds;
  result.metrics["label_image_check"] = c.metrics;
  if (with_quality_metrics) add_quality_metrics(warm, input, params, result, progress);
  return result;
}

}  // namespace brainshift
