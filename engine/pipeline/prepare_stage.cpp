#include "pipeline/prepare_stage.h"

#include "pipeline/preop_fluid_spaces_stage.h"
#include "pipeline/segmentation_rounds.h"
#include "pipeline/working_grid.h"
#include "protocol/stage_names.h"

#include <algorithm>
#include <cmath>
#include <optional>

#include "core/errors.h"
#include "core/timer.h"
#include "image/image_stats.h"
#include "image/resample.h"
#include "registration/affine_registration.h"
#include "segmentation/head_mask.h"
#include "segmentation/tissue_prior.h"

namespace brainshift {
namespace stages = protocol::stages;
namespace {

// A mask on a grid of the same extent (same_extent_grid), nearest voxel.
Mask resample_mask(const Mask& m, const Grid3& target) {
  return nonzero_mask(resample_nearest(as_labels(m), target));
}

// The image-only scan with its first round on the coarser prior grid
// (PassShortcuts::prior_spacing_mm): the head's placement, the first
// segmentation and its light pass there; the preop labels that pass carries
// are brought to the image's grid as the re-match's prior, and the re-match
// rounds and the answer are worked on the image's grid as before. The first
// round only makes that prior (1 mm wide; docs/DESIGN.md "Automatic intraop
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
  r.result.warped_labels = preop_labels_on_grid(warm, r.result.pullback_field_mm, image.grid);
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

ScanResult register_given_labels(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                 const ProgressFn& progress, bool with_quality_metrics) {
  // Labels alone take back the fluid spaces the preop counts as brain (the
  // preop's T1 tells fluid there); labels whose image the configuration
  // does not check them against are used as given.
  nlohmann::json fluid_spaces = {{"applied", false}, {"why", "labels used as given (check_given_labels off)"}};
  std::optional<IntraopInput> with_spaces;
  if (!input.t1) with_spaces = with_preop_fluid_spaces(warm, input, params, fluid_spaces);
  const IntraopInput& used = with_spaces ? *with_spaces : input;
  const bool spaces_added = fluid_spaces.value("added_ml", 0.0) > 0;
  ScanResult result = run_intraop_on_working_grid(warm, used, params, progress);
  // Labels no plausible affine maps the preop brain onto leave nothing to
  // deliver: the rigid part of that affine was 13-66 mm off on the suite's
  // segmenter's labels of a shaded image (docs/PERFORMANCE.md 12.43), and
  // without an image there is nothing else to place the preop by.
  if (!result.metrics["affine"].value("plausible", true))
    throw InputError("intraop labels: no plausible affine maps the preop brain onto them (" +
                     result.metrics["affine"].value("message", std::string()) +
                     "): they are not the brain the preop shows (segmented in part, or another scan's); "
                     "nothing was registered. Push the scan's image with them, or check the segmentation");
  result.metrics["given_labels"] = {{"use", "as given"}, {"preop_fluid_spaces", std::move(fluid_spaces)}};
  if (spaces_added) result.given_labels_used = used.labels;
  if (with_quality_metrics) add_quality_metrics(warm, used, params, result, progress);
  return result;
}

}  // namespace brainshift
