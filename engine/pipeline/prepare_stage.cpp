#include "pipeline/prepare_stage.h"
#include "pipeline/working_grid.h"
#include "protocol/stage_names.h"

#include <algorithm>
#include <cmath>
#include <future>
#include <optional>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "field/vector_sampling.h"
#include "field/warp.h"
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
  // Its volume scale is not the brain's: the gates take it out
  // (carried_preop_volumes).
  metrics = {{"converged", r.converged}, {"rms_surface_distance_mm", r.rms_surface_distance_mm},
             {"inlier_fraction", r.inlier_fraction}, {"message", r.message},
             {"volume_scale", placement.topLeftCorner<3, 3>().determinant()}};
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

// One image-only scan on the grid it is worked on: the preop carried there
// by the head's placement, and what the segmentation rounds and the passes
// of the stages share.
struct ScanOnGrid {
  WarmState& warm;
  const ImageF& image;
  double read_seconds;
  const PipelineParameters& params;
  const ProgressFn& progress;
  LabelImage carried;
  segmentation::PreopSeen seen;
  CarriedPreopVolumes carried_volumes;
  // The grid the passes' stages work on (PassShortcuts::stage_spacing_mm)
  // and the image there; the image's own grid (and no copy) when off.
  Grid3 stage_grid;
  std::optional<ImageF> stage_image;

  ScanOnGrid(WarmState& w, const ImageF& im, double read_s, const PipelineParameters& p, const ProgressFn& pr,
             const Eigen::Matrix4d& intraop_from_preop)
      : warm(w), image(im), read_seconds(read_s), params(p), progress(pr),
        carried(resample_nearest(w.preop.labels, im.grid, intraop_from_preop.inverse())),
        seen(preop_as_seen(w, p.label_table, carried, intraop_from_preop)),
        carried_volumes(carried_preop_volumes(carried, p.label_table,
                                              intraop_from_preop.topLeftCorner<3, 3>().determinant())),
        stage_grid(working_grid(im.grid, p.auto_segmentation.passes.stage_spacing_mm)) {
    if (stage_grid.dims != im.grid.dims) stage_image = downsample_linear(im, stage_grid);
  }

  // As for given labels (run_intraop), but said of the image and before the
  // segmentation's time is spent: the preop placed by the head shows how much
  // of the brain the field of view holds.
  void check_field_of_view() const {
    if (carried_volumes.brain_ml < params.gates.min_intraop_brain_fraction * warm.brain_volume_ml)
      throw InputError("intraop image: the field of view holds " + std::to_string(carried_volumes.brain_ml) +
                       " ml of the preop's " + std::to_string(warm.brain_volume_ml) +
                       " ml brain (placed by the head); it misses most of the brain");
  }

  // The prior a round is classified with: the preop placed by the head
  // (the first round's, wide) or carried by a non-rigid estimate (the
  // re-match's, narrow).
  enum class Prior { placed, carried };
  segmentation::IntraopSegmentation segment(const LabelImage& prior_labels, Prior prior, bool open_fluid_rule = true,
                                            const segmentation::IntraopSegmentation* fitted = nullptr,
                                            const Mask* gap_found_before = nullptr) const {
    const AutoSegmentationParameters& ap = params.auto_segmentation;
    segmentation::SegmentationParameters sp = ap.classifier;
    if (!open_fluid_rule) sp.max_sulcus_half_width_mm = 0;
    const bool placed = prior == Prior::placed;
    const double width_mm = placed ? ap.prior_width_affine_mm : ap.prior_width_nonrigid_mm;
    // The classified box ends where the prior meets its floor (docs/DESIGN.md
    // "Automatic intraop segmentation", item 7).
    sp.margin_mm = segmentation::prior_reach_mm(width_mm, sp.prior_floor);
    sp.prior_width_mm = width_mm;
    sp.ventricle_prior_width_mm = ap.ventricle_prior_width_mm;
    sp.ventricle_shift_mm = placed ? ap.ventricle_shift_affine_mm : 0.0;
    if (placed && sp.ventricle_shift_mm > 0) sp.prior_inward_width_mm = ap.prior_inward_width_affine_mm;
    sp.max_filled_hole_ml = params.min_resection_cavity_ml;
    const auto classify = [&](const segmentation::SegmentationParameters& with) {
      return segmentation::segment_intraop(image, prior_labels, params.label_table.brain_label(),
                                           ventricle_labels(params.label_table), with, fitted, gap_found_before, &seen);
    };
    auto seg = classify(sp);
    // A bright-fluid image under the wide prior: the bias is fitted again,
    // linear. The tissue that prior leaves uncertain (the fluid rim, oedema,
    // a resection's margin) is bright like the fluid there, and a quadratic
    // bent to it moved grey matter past half fluid (docs/DESIGN.md
    // "Automatic intraop segmentation", item 12). A refit the classifier
    // refuses leaves the first.
    const int degree = ap.bright_fluid_bias_degree_affine;
    if (placed && degree < sp.em.bias_degree && seg.refusal.empty() && segmentation::fluid_is_bright(seg.classes)) {
      sp.em.bias_degree = degree;
      auto linear = classify(sp);
      if (linear.refusal.empty()) {
        seg = std::move(linear);
        seg.report["bias_refitted"] = "bright fluid under the placed prior";
      }
    }
    return seg;
  }

  SegmentationGates gates(const segmentation::IntraopSegmentation& s, double open_fluid_ml) const {
    return check_segmentation(s.labels, s.confidence, carried_volumes, params.label_table, params.auto_segmentation,
                              open_fluid_ml);
  }

  // A pass a re-match follows only makes the re-match's prior: it runs light
  // (PassOptions::prior_only). A light pass the stages refuse is run again in
  // full when a shortcut changed its field, so that the shortcuts never
  // decide a refusal (nor its reason); a light pass that ends up the answer
  // (refused, or its re-match refused) is completed: by the outputs it
  // skipped when its field is a full pass's, else by the full pass.
  // A re-match's pass starts its affine from the pass before it (item 9).
  bool light_field_is_full() const {
    const auto& passes = params.auto_segmentation.passes;
    return passes.prior_refine && passes.prior_surface_max_iterations == 0;
  }
  ScanResult run_pass(const segmentation::IntraopSegmentation& s, bool rematch_follows, bool& prior_only,
                      const Eigen::Matrix4d* affine_start = nullptr) const {
    if (!params.auto_segmentation.passes.warm_start_affine) affine_start = nullptr;
    prior_only = false;
    if (rematch_follows) {
      ScanResult light = stages(s, "", PassOptions{true, affine_start});
      prior_only = light.kind == ResultKind::nonrigid;
      if (prior_only) return light;
      if (light_field_is_full()) {
        complete_prior_pass(warm, light, progress);
        return light;
      }
    }
    return stages(s, "", PassOptions{false, affine_start});
  }
  ScanResult refused(const segmentation::IntraopSegmentation& s, const std::string& reason) const {
    return stages(s, reason, PassOptions{});
  }
  // One pass of the stages on a segmentation. A full pass works on the stage
  // grid when that is coarser, its answer carried back to the image's grid
  // (metrics and timings "stage_grid"; the carrying counted in the pass's
  // total). A light pass stays on the image's grid: its warped labels are
  // the re-match's prior, whose outline at a deep sinking's edge the field
  // carried from 2 mm voxels moved by about a millimetre (the fade beyond the
  // mesh is steep there), enough to cost the re-match (docs/PERFORMANCE.md
  // 12.29).
  ScanResult stages(const segmentation::IntraopSegmentation& s, const std::string& forced,
                    const PassOptions& pass) const {
    if (!stage_image || pass.prior_only)
      return run_intraop(warm, IntraopInput{s.labels, image, read_seconds, s.open_fluid_ml}, params, progress, false,
                         forced, pass);
    Stopwatch watch;
    const IntraopInput coarser{downsample_labels(s.labels, stage_grid), *stage_image, read_seconds, s.open_fluid_ml};
    double own_seconds = watch.lap();
    ScanResult result = run_intraop(warm, coarser, params, progress, false, forced, pass);
    watch.lap();
    carry_to_grid(warm, result, image.grid);
    own_seconds += watch.lap();
    report_working_grid(result, stage_grid, image.grid, own_seconds, "stage_grid");
    return result;
  }
};

// A round's report: its prior's width and the bias fitted (and whether the
// first fit was replaced, ScanOnGrid::segment).
nlohmann::json round_report(const segmentation::IntraopSegmentation& s) {
  nlohmann::json r = {{"prior_width_mm", s.report["prior_width_mm"]}, {"bias_degree", s.report["bias_degree"]}};
  if (s.report.contains("bias_refitted")) r["bias_refitted"] = s.report["bias_refitted"];
  return r;
}

// The rounds of one scan so far: the segmentation that stands, its gates,
// the pass on it, and each round's report.
struct Rounds {
  segmentation::IntraopSegmentation seg;
  SegmentationGates gates;
  ScanResult result;
  bool result_prior_only = false;
  bool open_fluid_rule = true;
  nlohmann::json report = nlohmann::json::array();
  double segment_seconds = 0;
};

// The first round's segmentation and gates: the preop carried by the head's
// placement as the prior. A segmentation the classifier refuses is returned
// with its refusal (the caller decides). seconds_before: the scan's
// segmentation time so far (the head's placement).
Rounds first_segmentation(const ScanOnGrid& s, double seconds_before) {
  Rounds r;
  Stopwatch watch;
  r.seg = s.segment(s.carried, ScanOnGrid::Prior::placed);
  if (r.seg.refusal.empty()) r.gates = s.gates(r.seg, r.seg.open_fluid_ml);
  const double round_seconds = watch.lap();
  r.segment_seconds = seconds_before + round_seconds;
  if (s.progress) s.progress(std::string(stages::kSegment), 1.0, r.segment_seconds);
  nlohmann::json report = round_report(r.seg);
  report["gates"] = r.gates.metrics;
  report["seconds"] = round_seconds;
  r.report.push_back(std::move(report));
  return r;
}

// The first round's pass on a segmentation the classifier accepted, and the
// segmentation without the open-fluid rule where the stages refuse it.
// rematch_follows: the pass is light (ScanOnGrid::run_pass).
void first_pass(const ScanOnGrid& s, Rounds& r, bool rematch_follows) {
  Stopwatch watch;
  // The gates are checked before the stages, not beside them: every stage
  // already splits its work over both cores (the affine in every iteration),
  // and a third thread slowed them by more than the check costs.
  r.result = r.gates.failure.empty() ? s.run_pass(r.seg, rematch_follows, r.result_prior_only)
                                     : s.refused(r.seg, r.gates.failure);
  // The open-fluid rule reshapes the outline by shape, not by intensity
  // (docs/DESIGN.md "Automatic intraop segmentation", item 7); where the
  // stages refuse the field its outline gives (a fold: the cortex over a
  // resection cavity taken for the cap of a gap), the segmentation by the
  // image alone is tried once, and kept only if the stages accept it.
  if (r.result.kind == ResultKind::nonrigid || !r.gates.failure.empty() || r.seg.open_fluid_ml <= 0) return;
  watch.lap();
  auto plain = s.segment(s.carried, ScanOnGrid::Prior::placed, false);
  SegmentationGates plain_gates = s.gates(plain, 0.0);
  const double plain_seconds = watch.lap();
  r.segment_seconds += plain_seconds;
  nlohmann::json report = round_report(plain);
  report.update({{"gates", plain_gates.metrics}, {"open_fluid_rule", false}, {"refusal", plain.refusal},
                 {"seconds", plain_seconds}});
  r.report.push_back(std::move(report));
  if (plain.refusal.empty() && plain_gates.failure.empty()) {
    bool pass_prior_only = false;
    ScanResult pass = s.run_pass(plain, rematch_follows, pass_prior_only);
    if (pass.kind == ResultKind::nonrigid) {
      r.report.front()["kept"] = false;
      r.report.front()["fallback_reason"] = r.result.fallback_reason;
      r.open_fluid_rule = false;
      r.seg = std::move(plain);
      r.gates = std::move(plain_gates);
      r.result = std::move(pass);
      r.result_prior_only = pass_prior_only;
      return;
    }
  }
  r.report.back()["kept"] = false;
}

// The re-match rounds: the preop carried by the non-rigid estimate (the
// pass's own warped labels), a narrower prior, a smaller box. The gap a
// sinking left was found against the head's placement, as the gates
// measure: the first round's finding stands for the next.
// rematch_reuses_fit: the classes and bias fitted before are reused (off by
// default). A round the classifier, the gates or the stages refuse leaves
// the pass before it standing.
void rematch(const ScanOnGrid& s, Rounds& r) {
  const AutoSegmentationParameters& ap = s.params.auto_segmentation;
  Stopwatch watch;
  for (int round = 1; round <= ap.rematch_rounds && r.result.kind == ResultKind::nonrigid; ++round) {
    watch.lap();
    auto next = s.segment(r.result.warped_labels, ScanOnGrid::Prior::carried, r.open_fluid_rule,
                          ap.rematch_reuses_fit ? &r.seg : nullptr,
                          ap.rematch_gaps_found_before ? &r.seg.open_fluid : nullptr);
    next.open_fluid_ml = std::max(r.seg.open_fluid_ml, next.open_fluid_ml);
    SegmentationGates next_gates = s.gates(next, next.open_fluid_ml);
    const double round_seconds = watch.lap();
    r.segment_seconds += round_seconds;
    nlohmann::json report = round_report(next);
    report.update({{"gates", next_gates.metrics}, {"seconds", round_seconds}});
    ScanResult pass;
    bool pass_prior_only = false;
    bool refused = !next.refusal.empty() || !next_gates.failure.empty();
    if (refused) {
      report["refusal"] = next.refusal;
    } else {
      pass = s.run_pass(next, round < ap.rematch_rounds, pass_prior_only, &r.result.intraop_from_preop);
      refused = pass.kind != ResultKind::nonrigid;  // a fold
      if (refused) report["fallback_reason"] = pass.fallback_reason;
    }
    if (refused) {
      report["kept"] = false;
      r.report.push_back(report);
      break;
    }
    r.seg = std::move(next);
    r.gates = std::move(next_gates);
    r.result = std::move(pass);
    r.result_prior_only = pass_prior_only;
    r.report.push_back(report);
  }
}

// The answer from the rounds: the outputs a light pass skipped, the
// segmentation's report and time.
ScanResult answer(const ScanOnGrid& s, Rounds r, nlohmann::json seg_metrics, const Stopwatch& scan_watch,
                  bool with_quality_metrics) {
  if (r.result_prior_only && s.light_field_is_full()) {
    complete_prior_pass(s.warm, r.result, s.progress);
  } else if (r.result_prior_only) {  // the full pass on the segmentation that stands
    const Eigen::Matrix4d same_labels_affine = r.result.intraop_from_preop;
    bool unused = false;
    r.result = s.run_pass(r.seg, false, unused, &same_labels_affine);
  }
  ScanResult result = std::move(r.result);
  seg_metrics["classifier"] = r.seg.report;
  seg_metrics["gates"] = r.gates.metrics;
  seg_metrics["rounds"] = r.report;
  result.metrics["segmentation"] = seg_metrics;
  auto& t = result.timings["intraop"];
  t[std::string(stages::kSegment)] = r.segment_seconds;
  // Everything but the segmentation and the answer's own pass (whose total
  // includes the read) was an earlier pass.
  const double scan_seconds = scan_watch.seconds(), answer_pass_seconds = t.value("total", 0.0) - s.read_seconds;
  t["earlier_passes"] = std::max(0.0, scan_seconds - r.segment_seconds - answer_pass_seconds);
  t["total"] = scan_seconds + s.read_seconds;
  result.intraop_labels = std::move(r.seg.labels);
  result.segmentation_confidence = std::move(r.seg.confidence);
  if (with_quality_metrics)
    add_quality_metrics(s.warm, IntraopInput{*result.intraop_labels, s.image}, s.params, result, s.progress);
  return result;
}

// A mask on a grid of the same extent (same_extent_grid), nearest voxel.
Mask resample_mask(const Mask& m, const Grid3& target) {
  const LabelImage moved = resample_nearest(as_labels(m), target);
  Mask out(target, 0);
  for (std::size_t v = 0; v < out.voxels.size(); ++v) out.voxels[v] = moved.voxels[v] != 0;
  return out;
}

// The image-only scan with its first round on the coarser prior grid
// (PassShortcuts::prior_spacing_mm): the head's placement, the first
// segmentation and its light pass there; the preop labels that pass carries
// are brought to the image's grid as the re-match's prior, and the re-match
// rounds and the answer are worked on the image's grid as before. The first
// round only makes that prior (1.5 mm wide; docs/DESIGN.md "Automatic intraop
// segmentation", item 9). nullopt when the first round ends in a refusal (of
// the classifier, a gate or the stages): a refusal is decided on the image's
// own grid (the caller's one-grid path).
std::optional<ScanResult> register_with_coarse_prior(WarmState& warm, const ImageF& image, const Grid3& prior_grid,
                                                     double read_seconds, const PipelineParameters& params,
                                                     const ProgressFn& progress, bool with_quality_metrics,
                                                     const Stopwatch& scan_watch, nlohmann::json& prior_report) {
  Stopwatch watch;
  nlohmann::json seg_metrics;
  if (progress) progress(std::string(stages::kSegment), 0.0, 0.0);
  const ImageF coarse = downsample_linear(image, prior_grid);
  const Eigen::Matrix4d placement = place_preop_by_head(warm, coarse, params.affine, seg_metrics["head_placement"]);
  const ScanOnGrid first(warm, coarse, read_seconds, params, progress, placement);
  seg_metrics["head_placement"]["seconds"] = watch.seconds();
  first.check_field_of_view();
  Rounds r = first_segmentation(first, watch.lap());
  if (!r.seg.refusal.empty()) {
    prior_report["refused"] = "the classifier: " + r.seg.refusal;
  } else if (!r.gates.failure.empty()) {
    prior_report["refused"] = "the gates: " + r.gates.failure;
  } else {
    first_pass(first, r, true);
    if (r.result.kind != ResultKind::nonrigid) prior_report["refused"] = "the stages: " + r.result.fallback_reason;
  }
  if (prior_report.contains("refused")) return std::nullopt;
  watch.lap();
  const ScanOnGrid s(warm, image, read_seconds, params, progress, placement);
  r.result.warped_labels =
      warp_labels_nearest(warm.preop.labels, resample_vector_linear(r.result.pullback_field_mm, image.grid));
  if (r.seg.open_fluid.grid.voxel_count() > 0) r.seg.open_fluid = resample_mask(r.seg.open_fluid, image.grid);
  prior_report["carry_seconds"] = watch.lap();
  rematch(s, r);
  seg_metrics["prior_grid"] = prior_report;
  if (r.seg.labels.grid.same_geometry(image.grid))
    return answer(s, std::move(r), std::move(seg_metrics), scan_watch, with_quality_metrics);
  // Every re-match refused: the first round's answer, carried to the image's grid.
  ScanResult result = answer(first, std::move(r), std::move(seg_metrics), scan_watch, false);
  carry_to_grid(warm, result, image.grid);
  if (with_quality_metrics)
    add_quality_metrics(warm, IntraopInput{*result.intraop_labels, image}, params, result, progress);
  return result;
}

// The image-only scan on the image's own grid (see register_image_only).
ScanResult register_on_grid(WarmState& warm, const ImageF& image, double read_seconds, const PipelineParameters& params,
                            const ProgressFn& progress, bool with_quality_metrics) {
  const AutoSegmentationParameters& ap = params.auto_segmentation;
  if (image.grid.voxel_count() == 0) throw InputError("intraop image: the image has no voxels");
  for (float v : image.voxels)
    if (!std::isfinite(v)) throw InputError("intraop image: contains non-finite values");

  Stopwatch watch, scan_watch;
  nlohmann::json seg_metrics;
  const Grid3 prior_grid = working_grid(image.grid, ap.passes.prior_spacing_mm);
  if (ap.rematch_rounds > 0 && !ap.rematch_reuses_fit && prior_grid.dims != image.grid.dims) {
    nlohmann::json& prior = seg_metrics["prior_grid"];
    prior = {{"dims", {prior_grid.dims[0], prior_grid.dims[1], prior_grid.dims[2]}},
             {"spacing_mm", {prior_grid.spacing_mm()[0], prior_grid.spacing_mm()[1], prior_grid.spacing_mm()[2]}}};
    auto result = register_with_coarse_prior(warm, image, prior_grid, read_seconds, params, progress,
                                             with_quality_metrics, scan_watch, prior);
    if (result) return std::move(*result);
    prior["seconds"] = watch.lap();
  }
  if (progress) progress(std::string(stages::kSegment), 0.0, 0.0);
  const Eigen::Matrix4d placement = place_preop_by_head(warm, image, params.affine, seg_metrics["head_placement"]);
  const ScanOnGrid s(warm, image, read_seconds, params, progress, placement);
  seg_metrics["head_placement"]["seconds"] = watch.seconds();
  s.check_field_of_view();
  Rounds r = first_segmentation(s, watch.lap());
  if (!r.seg.refusal.empty()) throw InputError("intraop image: " + r.seg.refusal);
  first_pass(s, r, ap.rematch_rounds > 0);
  rematch(s, r);
  return answer(s, std::move(r), std::move(seg_metrics), scan_watch, with_quality_metrics);
}

// Labels given with their image, refined (GivenLabelsUse::refine) on the
// grid they were worked on: the labels' pass (first) carried the preop onto
// the image; the image is classified under that carried preop as a
// re-match round is (rematch: its narrow prior, its gates, one pass of the
// stages warm-started from the labels' affine) and that segmentation is
// registered. Two things differ from an image-only re-match (docs/DESIGN.md
// "Labels with their image"): no round of our own found the sinking's gap
// before, so the open-fluid rule acts as in a first round; and the volume
// gate's reference spans the preop's brain and the given labels' (a sinking
// shows in the labels, a segmenter's erosion at low field makes them
// smaller than the brain): the refined brain must lie within
// max_brain_volume_change of that span. nullopt, with the reason in
// `report`, when the classifier, a gate or the stages refuse it; `first` is
// then left as it was.
std::optional<ScanResult> refine_on_grid(WarmState& warm, const ImageF& image, const LabelImage& given,
                                         ScanResult& first, double read_seconds, const PipelineParameters& params,
                                         const ProgressFn& progress, const Stopwatch& scan_watch,
                                         nlohmann::json& report) {
  if (progress) progress(std::string(stages::kSegment), 0.0, 0.0);
  PipelineParameters p = params;
  p.auto_segmentation.rematch_gaps_found_before = false;
  ScanOnGrid s(warm, image, read_seconds, p, progress, first.intraop_from_preop);
  const double given_ml = carried_preop_volumes(given, params.label_table, 1.0).brain_ml;
  const double preop_ml = s.carried_volumes.brain_ml;
  Rounds r;
  // The gate's reference is the span's top; its lower bound's allowance (the
  // gap's, otherwise) reaches the span's bottom.
  s.carried_volumes.brain_ml = std::max(preop_ml, given_ml);
  r.seg.open_fluid_ml = std::abs(preop_ml - given_ml);
  report["brain_ml"] = {{"preop", preop_ml}, {"given", given_ml}};
  r.result = std::move(first);
  rematch(s, r);
  if (r.report.empty() || !r.report.back().value("kept", true)) {
    first = std::move(r.result);
    report["refused"] = r.report.empty() ? nlohmann::json("no re-match round (rematch_rounds = 0)") : r.report.back();
    return std::nullopt;
  }
  nlohmann::json seg_metrics;
  seg_metrics["prior"] = "the preop carried by the given labels' pass";
  return answer(s, std::move(r), std::move(seg_metrics), scan_watch, false);
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
  report_working_grid(result, work, image.grid, own_seconds);
  if (with_quality_metrics)
    add_quality_metrics(warm, IntraopInput{*result.intraop_labels, image}, params, result, progress);
  return result;
}

namespace {

// The labels' pass refined by the image (refine_on_grid), on the working
// grid when the labels' grid is finer (as an image-only scan is worked);
// the refined answer carried back to the labels' grid. `first` is replaced
// when the refinement stands and left as it was otherwise.
void refine_given_labels(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                         const ProgressFn& progress, const Stopwatch& scan_watch, ScanResult& first) {
  nlohmann::json report = {{"use", "refine"}};
  const double first_pass_seconds = first.timings["intraop"].value("total", 0.0);
  Stopwatch watch;
  const Grid3 work = working_grid(input.labels.grid, params.auto_segmentation.working_spacing_mm);
  std::optional<ScanResult> refined;
  if (work.dims == input.labels.grid.dims) {
    refined = refine_on_grid(warm, *input.t1, input.labels, first, input.read_seconds, params, progress, scan_watch,
                             report);
  } else {
    const ImageF image = downsample_linear(*input.t1, work);
    const LabelImage given = downsample_labels(input.labels, work);
    LabelImage warped_on_grid = std::move(first.warped_labels);
    first.warped_labels =
        warp_labels_nearest(warm.preop.labels, resample_vector_linear(first.pullback_field_mm, work));
    const double own_seconds = watch.lap();
    refined = refine_on_grid(warm, image, given, first, input.read_seconds, params, progress, scan_watch, report);
    if (refined) {
      watch.lap();
      carry_to_grid(warm, *refined, input.labels.grid);
      report_working_grid(*refined, work, input.labels.grid, own_seconds + watch.lap());
    } else {
      first.warped_labels = std::move(warped_on_grid);
    }
  }
  report["refined"] = refined.has_value();
  if (refined) {
    refined->timings["intraop"]["given_labels_pass"] = first_pass_seconds;
    first = std::move(*refined);
  }
  first.metrics["given_labels"] = std::move(report);
}

}  // namespace

ScanResult register_labels_with_image(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                      GivenLabelsUse use, const ProgressFn& progress, bool with_quality_metrics) {
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
  ScanResult result = run_intraop_on_working_grid(warm, input, params, progress);
  segmentation::LabelImageCheck c = check.get();
  if (!c.failure.empty() && result.kind == ResultKind::nonrigid) {
    const nlohmann::json first_timings = result.timings["intraop"];
    result = run_intraop_on_working_grid(warm, input, params, progress,
                                         "the intraop labels disagree with the intraop image: " + c.failure);
    result.timings["intraop"]["earlier_passes"] = first_timings.value("total", 0.0);
  } else if (use == GivenLabelsUse::refine && result.kind == ResultKind::nonrigid) {
    // Labels that disagree grossly with their image are not refined: the
    // answer says so (above). Labels whose own pass the gates refused are
    // not either: that refusal is the answer's, with its reason.
    refine_given_labels(warm, input, params, progress, watch, result);
  } else {
    result.metrics["given_labels"] = {{"use", std::string(to_string(use))}, {"refined", false}};
  }
  // The answer waits for the check: the wait is part of what the surgeon waits for.
  result.timings["intraop"][std::string(stages::kTotal)] = watch.seconds() + input.read_seconds;
  c.metrics["seconds"] = check_seconds;
  result.metrics["label_image_check"] = c.metrics;
  // The figures judge the labels the stages used: the refined segmentation
  // when it stands.
  if (with_quality_metrics)
    add_quality_metrics(warm, IntraopInput{result.intraop_labels ? *result.intraop_labels : input.labels, input.t1},
                        params, result, progress);
  return result;
}

ScanResult register_given_labels(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                 const ProgressFn& progress, bool with_quality_metrics) {
  ScanResult result = run_intraop_on_working_grid(warm, input, params, progress);
  if (with_quality_metrics) add_quality_metrics(warm, input, params, result, progress);
  return result;
}

}  // namespace brainshift
