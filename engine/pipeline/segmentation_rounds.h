#pragma once
// The segmentation rounds an image-only scan is made of (prepare_stage.h),
// and what a refinement of given labels by their image reuses
// (labels_with_image.h): the preop placed by the head, one scan on the grid
// it is worked on (ScanOnGrid: the carried preop, the segmentation of a
// round, its gates, the passes of the stages), the rounds so far and the
// answer made of them. Internal to the pipeline library.
#include <array>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "core/errors.h"
#include "core/timer.h"
#include "image/resample.h"
#include "pipeline/segmentation_gates.h"
#include "pipeline/warm_state.h"
#include "pipeline/working_grid.h"
#include "registration/affine_registration.h"
#include "segmentation/intraop_segmentation.h"
#include "segmentation/tissue_prior.h"

namespace brainshift {

// A mask as a label map (1 inside): head outlines for the label affine (no
// ventricle term, value 2 is absent), masks resampled by the nearest voxel.
LabelImage as_labels(const Mask& m);

// Two passes: the preop head seen through the identity (scanners place a
// patient's head within centimetres of the same RAS position) or, when that
// sees too little of it, the whole head; then seen through the first result.
Eigen::Matrix4d place_preop_by_head(WarmState& warm, const ImageF& image, const AffineRegistrationParameters& affine,
                                    nlohmann::json& metrics);

std::vector<std::uint16_t> ventricle_labels(const LabelTable& table);

// The preop T1's medians over its ventricles (fluid) and its brain label
// (tissue), once per preop; both 0 without ventricles in the preop labels.
const std::array<double, 2>& preop_fluid_tissue_medians(WarmState& warm, const LabelTable& table);

// The preop where the head's placement puts it (segmentation::PreopSeen):
// its T1 and its own fluid and tissue intensities. Without ventricles in the
// preop labels there is no fluid to compare with: the medians are equal and
// the test is off.
segmentation::PreopSeen preop_as_seen(WarmState& warm, const LabelTable& table, const LabelImage& carried,
                                      const Eigen::Matrix4d& intraop_from_preop);

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
    placement = intraop_from_preop;
  }
  // Where the head was placed (place_preop_by_head): one more start for the
  // passes' affine (PassOptions::affine_candidate).
  Eigen::Matrix4d placement = Eigen::Matrix4d::Identity();

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
                                            const Mask* gap_found_before = nullptr,
                                            const Eigen::Matrix4d* labels_affine = nullptr) const {
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
    if (!placed) sp.prior_inward_width_mm = ap.prior_inward_width_nonrigid_mm;
    // The rim's thick caps in a re-match only, where the carried outline is
    // the non-rigid estimate's (about 1 mm off): under the head placement's
    // wide prior they peeled tissue the truth calls brain on a T2 resection
    // (12 ml, family 6: 0.601 -> 0.675 mm) and moved the estimate the
    // re-match starts from (docs/PERFORMANCE.md 12.39).
    if (placed) sp.max_rim_cap_mm = 0;
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
    if (seg.refusal.empty())
      adopt_fluid_spaces(seg, labels_affine ? *labels_affine : Eigen::Matrix4d(seen.preop_from_intraop.inverse()));
    return seg;
  }

  // The preop's own fluid spaces (basal cisterns, the third ventricle, a
  // wide fissure) that the classification left outside: given back to the
  // brain as for given labels (segmentation/preop_fluid_spaces.h), placed
  // by intraop_from_preop: the head's placement in the first round, the
  // pass's label affine in a re-match.
  void adopt_fluid_spaces(segmentation::IntraopSegmentation& seg, const Eigen::Matrix4d& intraop_from_preop) const;

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
  ScanResult refused(const segmentation::IntraopSegmentation& s, const SegmentationGates& gates) const {
    PassOptions pass;
    pass.forced_fallback_rigid = gates.geometry_refused;
    return stages(s, gates.failure, pass);
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
                    PassOptions pass) const {
    pass.segmented_by_engine = true;
    pass.affine_candidate = &placement;
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

// The preop labels carried by a pass's field sampled trilinearly on another
// grid of the same extent (a coarser round's, or the labels' own): a
// re-match's prior there.
LabelImage preop_labels_on_grid(const WarmState& warm, const VectorImage3& pullback_field_mm, const Grid3& grid);

// The caution a non-rigid answer carries when the last re-match round was
// refused (`rounds`: metrics.segmentation.rounds; by the classifier, a gate
// or the stages): the answer then rests on the first round's segmentation,
// made under the head placement's wide prior (3 mm out, 5 mm in) on the
// coarser grid. In the suites that happened only on images the engine
// handles worst (a contrast-enhanced 0.15 T scan 2.6-3.9 mm off, a receive
// array's unnormalised shading 5.7 mm; docs/PERFORMANCE.md 12.43), on no
// plain T1, T2-like or FLAIR-like scan. Empty when the last round stands.
std::string refused_rematch_caution(const nlohmann::json& rounds);

// A round's report: its prior's width and the bias fitted (and whether the
// first fit was replaced, ScanOnGrid::segment).
nlohmann::json round_report(const segmentation::IntraopSegmentation& s);

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
Rounds first_segmentation(const ScanOnGrid& s, double seconds_before);

// The first round's pass on a segmentation the classifier accepted, and the
// segmentation without the open-fluid rule where the stages refuse it.
// rematch_follows: the pass is light (ScanOnGrid::run_pass).
void first_pass(const ScanOnGrid& s, Rounds& r, bool rematch_follows);

// The re-match rounds: the preop carried by the non-rigid estimate (the
// pass's own warped labels), a narrower prior, a smaller box. The gap a
// sinking left was found against the head's placement, as the gates
// measure: the first round's finding stands for the next.
// rematch_reuses_fit: the classes and bias fitted before are reused (off by
// default). A round the classifier, the gates or the stages refuse leaves
// the pass before it standing.
void rematch(const ScanOnGrid& s, Rounds& r);

// The answer from the rounds: the outputs a light pass skipped, the
// segmentation's report and time.
ScanResult answer(const ScanOnGrid& s, Rounds r, nlohmann::json seg_metrics, const Stopwatch& scan_watch,
                  bool with_quality_metrics);

}  // namespace brainshift
