#include "pipeline/labels_with_image.h"

#include <algorithm>
#include <cmath>
#include <future>
#include <optional>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "image/resample.h"
#include "pipeline/prepare_stage.h"
#include "pipeline/preop_fluid_spaces_stage.h"
#include "pipeline/segmentation_rounds.h"
#include "pipeline/working_grid.h"
#include "protocol/stage_names.h"
#include "quality/plausibility_gates.h"
#include "registration/affine_registration.h"
#include "registration/boundary_samples.h"
#include "segmentation/label_image_check.h"

namespace brainshift {
namespace stages = protocol::stages;
namespace {

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
  // The gate's reference is the span's top; its lower bound's allowance
  // reaches the span's bottom. Not as open fluid: that is what the stages'
  // own volume gate adds to the brain (fluid where the brain was).
  s.carried_volumes.brain_ml = std::max(preop_ml, given_ml);
  s.carried_volumes.lower_allowance_ml = std::abs(preop_ml - given_ml);
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

// What the image's refinement changed in the given labels, measured as the
// labels-vs-image check measures disagreement (its band, its sureness, its
// limit): brain the refined segmentation added beyond the band (a lobe the
// segmenter lost) and brain it removed (a leak). The refined answer stands
// on the image, so a lost lobe is no hazard to it; but the site's segmenter
// erred, and whoever reads the answer must see where and by how much (a
// lobe lost within the check's wide prior passes the check: 14 ml seen of a
// 144 ml ball, docs/PERFORMANCE.md 12.35). Beyond the check's limit the
// change is `gross` and the answer carries a `caution`. Cavity values are
// taken out of the given outline: the segmentation draws a cavity as 0.
nlohmann::json refinement_changes(const LabelImage& given, const ScanResult& refined, const LabelTable& table,
                                  const segmentation::LabelImageCheckParameters& p) {
  if (!refined.intraop_labels || !refined.segmentation_confidence) return {{"measured", false}};
  Stopwatch watch;
  LabelImage given_tissue = given;
  for (const std::uint16_t c : table.cavity_labels())
    for (auto& v : given_tissue.voxels)
      if (v == c) v = 0;
  const Mask given_brain = outline_mask(given_tissue);
  const Mask refined_brain = outline_mask(*refined.intraop_labels);
  const auto& confidence = *refined.segmentation_confidence;
  const segmentation::Disagreement added =
      segmentation::disagreement_beyond_band(refined_brain, given_brain, confidence, p.min_posterior, p.band_mm);
  const segmentation::Disagreement removed =
      segmentation::disagreement_beyond_band(given_brain, refined_brain, confidence, p.min_posterior, p.band_mm);
  const double limit_ml = p.max_disagreement_fraction * volume_ml(given_brain);
  nlohmann::json j = {{"measured", true},
                      {"added", segmentation::to_json(added)},
                      {"removed", segmentation::to_json(removed)},
                      {"band_mm", p.band_mm},
                      {"limit_ml", limit_ml},
                      {"seconds", watch.seconds()}};
  const auto where = [&](const segmentation::Disagreement& d) { return segmentation::to_text(d, p.band_mm); };
  std::string caution;
  if (added.volume_ml > limit_ml) caution = "brain the given labels lack: " + where(added);
  if (removed.volume_ml > limit_ml)
    caution += (caution.empty() ? "" : "; ") + std::string("labelled brain the image does not show: ") + where(removed);
  j["gross"] = !caution.empty();
  if (!caution.empty())
    j["caution"] = "the image's segmentation was registered, not the given labels, which disagree with it: " + caution;
  return j;
}

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
  const segmentation::LabelImageCheckParameters& check = params.auto_segmentation.label_image_check;
  std::optional<ScanResult> refined;
  if (work.dims == input.labels.grid.dims) {
    refined = refine_on_grid(warm, *input.t1, input.labels, first, input.read_seconds, params, progress, scan_watch,
                             report);
    if (refined) report["changes"] = refinement_changes(input.labels, *refined, params.label_table, check);
  } else {
    const ImageF image = downsample_linear(*input.t1, work);
    const LabelImage given = downsample_labels(input.labels, work);
    LabelImage warped_on_grid = std::move(first.warped_labels);
    first.warped_labels = preop_labels_on_grid(warm, first.pullback_field_mm, work);
    const double own_seconds = watch.lap();
    refined = refine_on_grid(warm, image, given, first, input.read_seconds, params, progress, scan_watch, report);
    if (refined) {
      report["changes"] = refinement_changes(given, *refined, params.label_table, check);
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
    // Beside "result": a non-rigid answer to be read with care.
    if (report["changes"].value("gross", false)) add_caution(first.metrics, report["changes"]["caution"]);
  }
  first.metrics["given_labels"] = std::move(report);
}

// The brain's affine registered on the image's own segmentation, as an
// image-only scan begins, on the first round's grid: the preop head placed
// on the image (place_preop_by_head), the first round's segmentation under
// that placement, the brain's affine on that segmentation. The
// segmentation's own gates are reported, not obeyed: they judge a
// segmentation to be registered non-rigidly, and a brain a tenth too small
// still has its place and axes. The head's placement alone is not enough:
// on the test's head, whose scan cuts the skull, its rigid part was 6 mm
// off. nullopt, with the reason in `report`, when the classifier refuses
// the image or the affine does not converge.
std::optional<Eigen::Matrix4d> image_own_affine(WarmState& warm, const ImageF& image, const PipelineParameters& params,
                                                nlohmann::json& report) {
  try {
    const Grid3 grid = working_grid(image.grid, params.auto_segmentation.passes.prior_spacing_mm);
    const ImageF coarse = grid.dims == image.grid.dims ? image : downsample_linear(image, grid);
    const Eigen::Matrix4d placement = place_preop_by_head(warm, coarse, params.affine, report["head_placement"]);
    const ProgressFn silent;  // ScanOnGrid keeps a reference
    const ScanOnGrid s(warm, coarse, 0.0, params, silent, placement);
    const Rounds r = first_segmentation(s, 0.0);
    if (!r.seg.refusal.empty()) throw ComputeError("the classifier refused the image: " + r.seg.refusal);
    if (!r.gates.failure.empty()) report["segmentation_gates"] = r.gates.failure;
    const auto cavities = params.label_table.cavity_labels();
    const IntraopDistanceMaps maps = prepare_intraop_maps(r.seg.labels, outline_mask(r.seg.labels),
                                                          params.label_table.brain_label(),
                                                          cavities.empty() ? 0 : cavities.front());
    const AffineRegistrationResult a = register_affine(warm.affine_samples, maps, params.affine, &placement);
    report["converged"] = a.converged;
    report["rms_surface_distance_mm"] = a.rms_surface_distance_mm;
    if (!a.converged) throw ComputeError("the brain's affine on the image's segmentation did not converge");
    return a.intraop_from_preop;
  } catch (const std::exception& e) {
    report["error"] = e.what();
  }
  return std::nullopt;
}

// The fallback's transform for labels refused with their image (by the
// check, or by the gates that judge their geometry): they may not even lie
// where their image does (shifted, mirrored, another scan's), so the affine
// fitted to them is not trusted, its rigid part included. The rigid part of
// the image's own affine is delivered (a head does not change size between
// two scans); when the image gives none, the labels' affine's rigid part.
FallbackTransform image_fallback(const WarmState& warm, const std::optional<Eigen::Matrix4d>& image_affine,
                                 const Eigen::Matrix4d& labels_affine, const std::string& why) {
  const Eigen::Vector3d centre_mm = warm.affine_samples.outer_moments.centroid_mm;
  if (image_affine)
    return {rigid_part(*image_affine, centre_mm),
            "rigid part of the affine registered on the intraop image's own segmentation (" + why + ")"};
  return {rigid_part(labels_affine, centre_mm), "rigid part of the labels' affine (" + why + "; the image gave no affine)"};
}

// The labels' own pass refused because a surface of theirs lies beyond
// what any deformation of the preop's reaches (the residual gate: a mean
// residual over three voxels of segmentation noise). That says something
// against the labels (a segmenter's lost horn or lobe; held-out family 28,
// docs/PERFORMANCE.md 12.47), unlike a fold or a solver failure, which the
// image's own segmentation could meet as well. The surface the gate named.
std::string unreachable_surface(const nlohmann::json& metrics, double max_mean_residual_mm) {
  if (!metrics.contains("surfaces") || !metrics["surfaces"].is_object()) return {};
  for (const auto& [name, m] : metrics["surfaces"].items())
    if (m.is_object() && m.value("matched", false) && m.value("mean_residual_mm", 0.0) > max_mean_residual_mm)
      return name;
  return {};
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
  // The fluid spaces are given back while the check runs on the other core.
  nlohmann::json fluid_spaces = {{"applied", false}, {"why", "labels used exactly"}};
  std::optional<IntraopInput> with_spaces;
  if (use == GivenLabelsUse::refine) with_spaces = with_preop_fluid_spaces(warm, input, params, fluid_spaces);
  const IntraopInput& adopted = with_spaces ? *with_spaces : input;
  const bool spaces_added = fluid_spaces.value("added_ml", 0.0) > 0;
  // Labels their image will refine make the refinement's prior: their pass
  // is not guarded (PassOptions::guard_tissue); it is run again guarded when
  // it ends up the answer.
  PassOptions labels_pass;
  labels_pass.guard_tissue = use != GivenLabelsUse::refine;
  ScanResult result = run_intraop_on_working_grid(warm, adopted, params, progress, "", labels_pass);
  segmentation::LabelImageCheck c = check.get();
  // The labels refused: the fallback's transform comes from their image
  // (image_fallback), whether the check or the gates judging the labels'
  // geometry refused them.
  const auto fall_back_on_the_image = [&](const std::string& reason, const std::string& why) {
    const nlohmann::json first_timings = result.timings["intraop"];
    PassOptions refused;
    nlohmann::json from_image;
    const auto image_affine = image_own_affine(warm, *input.t1, params, from_image);
    refused.forced_fallback_transform = image_fallback(warm, image_affine, result.intraop_from_preop, why);
    result = run_intraop_on_working_grid(warm, adopted, params, progress, reason, refused);
    result.metrics["affine"]["fallback_from_image"] = std::move(from_image);
    result.timings["intraop"]["earlier_passes"] = first_timings.value("total", 0.0);
  };
  // run_intraop names a fallback transform only after the gates refused
  // the labels' geometry (volume, affine_stretch).
  const bool geometry_refused =
      result.kind != ResultKind::nonrigid && result.metrics["affine"].contains("fallback_transform");
  // Labels to be refined by their image that are refused (by the check, or
  // by the gates that judge their geometry) give way to the image alone:
  // the site asked for the image's judgement, and the image's own answer
  // (validated as image-only scans are) is far nearer the truth than any
  // transform from the refused labels (docs/DESIGN.md "Labels with their
  // image"). The answer is non-rigid with a caution, never clean. Labels
  // used exactly (a site's hand correction) are not replaced: the marked
  // fallback, with the reason.
  std::string image_alone_refused;  // why the image's own answer was not taken
  const auto answer_from_the_image = [&](const std::string& why) {
    const nlohmann::json first_timings = result.timings["intraop"];
    std::optional<ScanResult> own;
    try {
      own = register_image_only(warm, *input.t1, input.read_seconds, params, progress, false);
    } catch (const InputError& e) {  // the image cannot be classified: the labels' fallback stands
      image_alone_refused = e.what();
      return false;
    }
    if (own->kind != ResultKind::nonrigid) {
      image_alone_refused = own->fallback_reason;
      return false;
    }
    result = std::move(*own);
    result.timings["intraop"]["earlier_passes"] = first_timings.value("total", 0.0);
    result.metrics["given_labels"] = {{"use", std::string(to_string(use))},
                                      {"refined", false},
                                      {"disregarded", true},
                                      {"why", why}};
    add_caution(result.metrics,
                "the given labels were disregarded (" + why + "); the image's own segmentation was registered");
    return true;
  };
  const bool check_refused = !c.failure.empty();
  const std::string unreachable = result.kind == ResultKind::nonrigid
                                      ? std::string()
                                      : unreachable_surface(result.metrics, params.gates.max_mean_surface_residual_mm);
  bool disregarded = false;
  // Only refusals of the labels themselves (the check, the gates on their
  // geometry, a surface of theirs out of reach): a fold or a solver failure
  // in their pass says nothing against them, and its fallback stands.
  if (use == GivenLabelsUse::refine && (check_refused || geometry_refused || !unreachable.empty()))
    disregarded = answer_from_the_image(
        check_refused      ? "they disagree with their image: " + c.failure
        : geometry_refused ? "the gates refused their geometry: " + result.fallback_reason
                           : "no deformation of the preop reaches their " + unreachable + " (" +
                                 result.fallback_reason + ")");
  const auto refused_labels = [&](const std::string& why) {
    result.metrics["given_labels"] = {{"use", std::string(to_string(use))}, {"refined", false}, {"why", why}};
    if (!image_alone_refused.empty()) result.metrics["given_labels"]["image_alone_refused"] = image_alone_refused;
  };
  if (disregarded) {
    // The image's own answer stands, with its caution (answer_from_the_image).
  } else if (check_refused && result.kind == ResultKind::nonrigid) {
    fall_back_on_the_image("the intraop labels disagree with the intraop image: " + c.failure,
                           "the labels disagree with their image");
    refused_labels("the labels disagree grossly with their image (label_image_check)");
  } else if (geometry_refused) {
    fall_back_on_the_image(result.fallback_reason, "the labels' geometry was refused");
    refused_labels("the gates refused the labels' geometry");
  } else if (use == GivenLabelsUse::refine && result.kind == ResultKind::nonrigid) {
    // Only labels that passed the check and their own pass get here: refused
    // ones gave way to the image, or (the image refused too) to the
    // fallback above.
    refine_given_labels(warm, adopted, params, progress, watch, result);
    if (!result.metrics["given_labels"].value("refined", false)) {
      nlohmann::json given_labels = result.metrics["given_labels"];
      const double before = watch.seconds();
      result = run_intraop_on_working_grid(warm, adopted, params, progress);
      result.timings["intraop"]["earlier_passes"] = before;
      result.metrics["given_labels"] = std::move(given_labels);
    }
  } else {
    result.metrics["given_labels"] = {{"use", std::string(to_string(use))}, {"refined", false}};
    if (!image_alone_refused.empty()) result.metrics["given_labels"]["image_alone_refused"] = image_alone_refused;
  }
  result.metrics["given_labels"]["preop_fluid_spaces"] = std::move(fluid_spaces);
  if (spaces_added && !result.intraop_labels) result.given_labels_used = adopted.labels;
  // The answer waits for the check: the wait is part of what the surgeon waits for.
  result.timings["intraop"][std::string(stages::kTotal)] = watch.seconds() + input.read_seconds;
  c.metrics["seconds"] = check_seconds;
  result.metrics["label_image_check"] = c.metrics;
  // The figures judge the labels the stages used: the refined segmentation
  // when it stands.
  if (with_quality_metrics)
    add_quality_metrics(warm,
                        IntraopInput{result.intraop_labels ? *result.intraop_labels : adopted.labels, input.t1},
                        params, result, progress);
  return result;
}

}  // namespace brainshift
