#include "pipeline/segmentation_rounds.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "core/errors.h"
#include "core/rotation_angle.h"
#include "core/timer.h"
#include "field/vector_sampling.h"
#include "field/warp.h"
#include "image/image_stats.h"
#include "protocol/stage_names.h"
#include "registration/intensity_placement.h"
#include "segmentation/enhanced_shell.h"
#include "segmentation/head_mask.h"
#include "segmentation/preop_fluid_spaces.h"

namespace brainshift {
namespace stages = protocol::stages;
namespace {

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

}  // namespace

// Head outlines as label maps (1 = head) for the label affine; no ventricle
// term (value 2 is absent).
LabelImage as_labels(const Mask& m) {
  LabelImage out(m.grid, 0);
  for (std::size_t v = 0; v < m.voxels.size(); ++v) out.voxels[v] = m.voxels[v] ? 1 : 0;
  return out;
}

// A head mask at most this many times the preop brain's volume is a brain,
// not a head: scalp, skull and the CSF round a brain (a sphere of some 70 mm
// radius) are at least 10 mm thick, so a whole head holds (80 / 70)^3 = 1.5
// times the brain or more (the face and neck add to it), while a
// brain-extracted image keeps the brain and a little CSF (1.0-1.2).
constexpr double kBrainExtractedHeadRatio = 1.35;

namespace {

// A pose the search finds more than this far from the placement it starts
// from is another pose, not the same one refined: half the search's yaw
// step (registration/intensity_placement.h), the most a candidate lies from
// the pose it stands for.
constexpr double kOtherPoseDeg = 15.0;

const IntensityPlacementPreop& placement_samples(WarmState& warm) {
  if (!warm.intensity_placement_preop)
    warm.intensity_placement_preop = intensity_placement_preop(warm.preop.t1, nonzero_mask(warm.preop.labels));
  return *warm.intensity_placement_preop;
}

nlohmann::json describe(const PoseSearch& s) {
  return {{"best_candidate_rotation_deg", s.rotation_from_start_deg},
          {"best_candidate_correlation", s.correlation},
          {"candidates", s.candidates},
          {"evaluations", s.evaluations},
          {"seconds", s.seconds}};
}

// The pose an earlier scan of this preop checked, when the placement is
// within kOtherPoseDeg of it (WarmState::checked_head_pose).
bool pose_checked_before(const WarmState& warm, const Eigen::Matrix4d& placement) {
  return warm.checked_head_pose &&
         rotation_between_deg(warm.checked_head_pose->topLeftCorner<3, 3>(), placement.topLeftCorner<3, 3>()) <=
             kOtherPoseDeg;
}

nlohmann::json checked_before_report(const std::string& used) {
  return {{"used", used},
          {"checked", "on an earlier scan of this preop: the head's pose then, within " +
                          std::to_string(static_cast<int>(kOtherPoseDeg)) + " degrees"}};
}

// The preop placed by its T1's intensities (registration/intensity_placement.h)
// when one of the two images has no head to match: a brain-extracted preop
// T1 (or scan). The head outlines would match a brain to a head and shrink it
// onto the scalp. From the pose an earlier scan found (the head stays in its
// clamp) or the scanner's placement; then, unless an earlier scan checked
// that pose, from the best pose of the search when that is another pose:
// the one that correlates better.
Eigen::Matrix4d place_preop_by_intensity(WarmState& warm, const ImageF& image, const std::string& why,
                                         nlohmann::json& metrics) {
  const IntensityPlacementPreop& samples = placement_samples(warm);
  const Eigen::Matrix4d start = warm.checked_head_pose ? *warm.checked_head_pose : Eigen::Matrix4d::Identity();
  const IntensityPlacementScan scan = intensity_placement_scan(samples, image);
  IntensityPlacement r = place_by_intensity(samples, scan, start);
  nlohmann::json pose;
  if (pose_checked_before(warm, r.intraop_from_preop)) {
    pose = checked_before_report("the earlier scan's pose, refined");
  } else {
    const PoseSearch search = search_pose_by_intensity(samples, scan, r.intraop_from_preop);
    pose = describe(search);
    pose["used"] = "the scanner's placement, refined";
    if (search.rotation_from_start_deg > kOtherPoseDeg) {
      IntensityPlacement other = place_by_intensity(samples, scan, search.intraop_from_preop);
      pose["other_pose_correlation"] = other.correlation;
      if (other.correlation * other.correlation > r.correlation * r.correlation) {
        other.evaluations += r.evaluations;
        r = std::move(other);
        pose["used"] = "the pose the search found, refined";
      }
    }
    warm.checked_head_pose = r.intraop_from_preop;
  }
  metrics = {{"by", "intensity"},
             {"why", why},
             {"correlation", r.correlation},
             {"inside_fraction", r.inside_fraction},
             {"evaluations", r.evaluations},
             {"message", r.message},
             {"pose_search", pose},
             {"volume_scale", r.intraop_from_preop.topLeftCorner<3, 3>().determinant()}};
  return r.intraop_from_preop;
}

// The outlines' match is local: a head turned in its clamp (a lateral
// approach, 60-90 degrees) leaves it in another pose, which the search by
// intensity finds (registration/intensity_placement.h). The outlines are
// then matched again from the pose it found, and whichever placement the
// preop brain's intensities correlate with better is kept.
nlohmann::json checked_pose(WarmState& warm, const ImageF& image, const IntraopDistanceMaps& maps,
                            const AffineRegistrationParameters& p, Eigen::Matrix4d& placement,
                            AffineRegistrationResult& r) {
  const IntensityPlacementPreop& intensity = placement_samples(warm);
  const IntensityPlacementScan scan = intensity_placement_scan(intensity, image);
  const double outline_correlation = intensity_correlation(intensity, scan, placement);
  const PoseSearch search = search_pose_by_intensity(intensity, scan, placement);
  nlohmann::json pose = describe(search);
  pose["outline_correlation"] = outline_correlation;
  pose["used"] = "the outlines' match";
  if (search.rotation_from_start_deg <= kOtherPoseDeg) return pose;
  const IntensityPlacement other = place_by_intensity(intensity, scan, search.intraop_from_preop);
  pose["other_pose_correlation"] = other.correlation;
  const PreopBoundarySamples samples = visible_head(*warm.preop_head, image.grid, &other.intraop_from_preop);
  const AffineRegistrationResult again = samples.outer_mm.size() < 100
                                             ? AffineRegistrationResult{}
                                             : register_affine(samples, maps, p, &other.intraop_from_preop);
  const double again_correlation = again.converged ? intensity_correlation(intensity, scan, again.intraop_from_preop) : 0.0;
  pose["other_pose_outline_correlation"] = again_correlation;
  const double best_so_far = outline_correlation * outline_correlation;
  if (again.converged && again_correlation * again_correlation > best_so_far) {
    r = again;
    placement = r.intraop_from_preop;
    pose["used"] = "the outlines' match from the pose the search found";
  } else if (other.correlation * other.correlation > best_so_far) {
    placement = other.intraop_from_preop;
    pose["used"] = "the pose the search found, refined by intensity";
  }
  return pose;
}

}  // namespace

// Two passes: the preop head seen through the identity (scanners place a
// patient's head within centimetres of the same RAS position) or, when that
// sees too little of it, the whole head; then seen through the first result.
// When either image is brain-extracted, by intensity instead.
Eigen::Matrix4d place_preop_by_head(WarmState& warm, const ImageF& image, const AffineRegistrationParameters& affine,
                                    nlohmann::json& metrics) {
  if (!warm.preop_head) {
    warm.preop_head = segmentation::head_mask(warm.preop.t1);
    if (count_nonzero(*warm.preop_head) == 0) throw ComputeError("the preop image shows no head (flat image)");
  }
  const Mask head = segmentation::head_mask(image);
  if (count_nonzero(head) == 0) throw InputError("intraop image: no head found (the image is flat)");
  // Outlines of the same kind (two heads, or two brains) are matched; a
  // brain to a head is not. A scan's head is also small when its field of
  // view cuts the head (a slab, a short coil): then only a brain-extracted
  // preop sends it here, where the correlation ignores what is out of view.
  const double preop_brain_ml = warm.brain_volume_ml;
  const bool preop_is_brain = volume_ml(*warm.preop_head) < kBrainExtractedHeadRatio * preop_brain_ml;
  const bool scan_is_brain = volume_ml(head) < kBrainExtractedHeadRatio * preop_brain_ml;
  if (preop_is_brain && !scan_is_brain)
    return place_preop_by_intensity(warm, image, "the preop T1 is brain-extracted (its head is its brain)", metrics);
  if (!preop_is_brain && scan_is_brain)
    return place_preop_by_intensity(warm, image,
                                    "the intraop image's head is the size of a brain (brain-extracted, or cut by "
                                    "its field of view)",
                                    metrics);
  const IntraopDistanceMaps maps = prepare_intraop_maps(as_labels(head), 1, 2);
  // The full affine, not a placement's (placement_affine), though the
  // placement only has to put the brain within the first round's 3 mm
  // prior: with a quarter of the points (0.07 s less per scan) the test
  // head's pure translation came back 0.59 mm off instead of 0.46
  // (docs/PERFORMANCE.md 12.39); the first round's outline carries into
  // the answer.
  AffineRegistrationParameters p = affine;
  p.ventricle_weight = 0;
  Eigen::Matrix4d placement = Eigen::Matrix4d::Identity();
  AffineRegistrationResult r;
  nlohmann::json pose;
  for (int pass = 0; pass < 2; ++pass) {
    PreopBoundarySamples samples = visible_head(*warm.preop_head, image.grid, &placement);
    if (pass == 0 && samples.outer_moments.volume_ml < 0.5 * volume_ml(head))
      samples = visible_head(*warm.preop_head, image.grid, nullptr);
    if (samples.outer_mm.size() < 100) break;
    r = register_affine(samples, maps, p);
    placement = r.intraop_from_preop;
  }
  // The placement checked against the head's other poses (checked_pose),
  // once per pose.
  if (pose_checked_before(warm, placement)) {
    pose = checked_before_report("the outlines' match");
  } else {
    pose = checked_pose(warm, image, maps, p, placement, r);
    warm.checked_head_pose = placement;
  }
  // Its volume scale is not the brain's: the gates take it out
  // (carried_preop_volumes).
  metrics = {{"converged", r.converged}, {"rms_surface_distance_mm", r.rms_surface_distance_mm},
             {"inlier_fraction", r.inlier_fraction}, {"message", r.message}, {"pose_search", pose},
             {"volume_scale", placement.topLeftCorner<3, 3>().determinant()}};
  return placement;
}

std::vector<std::uint16_t> ventricle_labels(const LabelTable& table) { return table.cavity_labels(); }

// The preop where the head's placement puts it (segmentation::PreopSeen):
// its T1 and its own fluid and tissue intensities. Without ventricles in the
// preop labels there is no fluid to compare with: the medians are equal and
// the test is off.
const std::array<double, 2>& preop_fluid_tissue_medians(WarmState& warm, const LabelTable& table) {
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
  return *warm.preop_fluid_tissue_medians;
}

segmentation::PreopSeen preop_as_seen(WarmState& warm, const LabelTable& table, const LabelImage& carried,
                                      const Eigen::Matrix4d& intraop_from_preop) {
  const auto& medians = preop_fluid_tissue_medians(warm, table);
  segmentation::PreopSeen seen;
  seen.image = &warm.preop.t1;
  seen.preop_from_intraop = intraop_from_preop.inverse();
  seen.fluid_median = medians[0];
  seen.tissue_median = medians[1];
  const auto resectable = table.resectable_labels();
  if (!resectable.empty()) seen.resectable = mask_of_labels(carried, resectable);
  return seen;
}

LabelImage preop_labels_on_grid(const WarmState& warm, const VectorImage3& pullback_field_mm, const Grid3& grid) {
  return warp_labels_nearest(warm.preop.labels, resample_vector_linear(pullback_field_mm, grid));
}

// The preop's fluid spaces given back (segmentation_rounds.h): the same
// test as for given labels.
void ScanOnGrid::adopt_fluid_spaces(segmentation::IntraopSegmentation& seg,
                                  const Eigen::Matrix4d& intraop_from_preop) const {
  const auto& table = params.label_table;
  const auto cavities = table.cavity_labels();
  const auto& medians = preop_fluid_tissue_medians(warm, table);
  if (medians[0] == medians[1]) return;
  const segmentation::PreopFluidSpacesInput in{seg.labels,        &image,
                                               warm.preop.labels, warm.preop.t1,
                                               intraop_from_preop, table.brain_label(),
                                               cavities.empty() ? std::uint16_t{0} : cavities.front(),
                                               medians[0],        medians[1]};
  const Stopwatch watch;
  segmentation::PreopFluidSpaces spaces = segmentation::adopt_preop_fluid_spaces(in, {});
  spaces.report["seconds"] = watch.seconds();
  if (spaces.added_ml > 0) {
    for (std::size_t v = 0; v < seg.labels.voxels.size(); ++v)
      if (spaces.labels.voxels[v] != seg.labels.voxels[v]) seg.confidence.voxels[v] = 1.f - seg.confidence.voxels[v];
    seg.labels = std::move(spaces.labels);
  }
  seg.report["preop_fluid_spaces"] = std::move(spaces.report);
}

// A round's report: its prior's widths outside and inside the carried
// outline and the bias fitted (and whether the first fit was replaced,
// ScanOnGrid::segment).
nlohmann::json round_report(const segmentation::IntraopSegmentation& s) {
  nlohmann::json r = {{"prior_width_mm", s.report["prior_width_mm"]},
                      {"prior_inward_width_mm", s.report["prior_inward_width_mm"]},
                      {"bias_degree", s.report["bias_degree"]}};
  if (s.report.contains("bias_refitted")) r["bias_refitted"] = s.report["bias_refitted"];
  return r;
}

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
                                     : s.refused(r.seg, r.gates);
  // The open-fluid rule reshapes the outline by shape, not by intensity
  // (docs/DESIGN.md "Automatic intraop segmentation", item 7); where the
  // stages refuse the field its outline gives (a fold: the cortex over a
  // resection cavity taken for the cap of a gap), the segmentation by the
  // image alone is tried once, and kept only if the stages accept it.
  if (r.result.kind == ResultKind::nonrigid || !r.gates.failure.empty() || r.seg.open_fluid_ml <= 0) return;
  watch.lap();
  if (s.progress) s.progress(std::string(stages::kSegment), 0.0, 0.0);
  auto plain = s.segment(s.carried, ScanOnGrid::Prior::placed, false);
  SegmentationGates plain_gates = s.gates(plain, 0.0);
  const double plain_seconds = watch.lap();
  r.segment_seconds += plain_seconds;
  if (s.progress) s.progress(std::string(stages::kSegment), 1.0, plain_seconds);
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
    // Each round is a line of its own in the timing log (PROTOCOL.md 8.2).
    if (s.progress) s.progress(std::string(stages::kSegment), 0.0, 0.0);
    auto next = s.segment(r.result.warped_labels, ScanOnGrid::Prior::carried, r.open_fluid_rule,
                          ap.rematch_reuses_fit ? &r.seg : nullptr,
                          ap.rematch_gaps_found_before ? &r.seg.open_fluid : nullptr, &r.result.intraop_from_preop);
    next.open_fluid_ml = std::max(r.seg.open_fluid_ml, next.open_fluid_ml);
    SegmentationGates next_gates = s.gates(next, next.open_fluid_ml);
    const double round_seconds = watch.lap();
    r.segment_seconds += round_seconds;
    if (s.progress) s.progress(std::string(stages::kSegment), 1.0, round_seconds);
    nlohmann::json report = round_report(next);
    report.update({{"gates", next_gates.metrics}, {"seconds", round_seconds}});
    ScanResult pass;
    bool pass_prior_only = false;
    bool refused = !next.refusal.empty() || !next_gates.failure.empty();
    if (refused) {
      report["refusal"] = next.refusal.empty() ? next_gates.failure : next.refusal;
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

std::string refused_rematch_caution(const nlohmann::json& rounds) {
  if (!rounds.is_array() || rounds.size() < 2 || rounds.back().value("kept", true)) return {};
  std::string why = rounds.back().value("refusal", std::string());
  if (why.empty()) why = rounds.back().value("fallback_reason", std::string());
  const std::string before = rounds.size() == 2 ? "the first round's, drawn under the head placement's wide prior"
                                                : "the round's before it";
  return "the re-match's segmentation was refused (" + why + "); the answer rests on " + before +
         ", not looked at again: it may be millimetres off at the surface";
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
  // Plausibility of the image, not agreement with it: a bright shell round
  // the brain (an enhancing dura) is classified with it (enhanced_shell.h).
  const Stopwatch shell_watch;
  const segmentation::EnhancedShell shell =
      segmentation::enhanced_shell(s.image, r.seg.bias, outline_mask(r.seg.labels), r.seg.classes);
  seg_metrics["enhanced_shell"] = shell.metrics;
  seg_metrics["enhanced_shell"]["seconds"] = shell_watch.seconds();
  if (shell.enhanced) {
    char ratio[16];
    std::snprintf(ratio, sizeof ratio, "%.2f", shell.surface_ratio);
    add_caution(result.metrics,
                "the image looks contrast-enhanced (" + std::to_string(static_cast<int>(100 * shell.bright_fraction)) +
                    " % of the tissue 1.5-3 mm outside the brain as bright as brain, the brain's outer layer " +
                    ratio +
                    " x as bright as the cortex beneath: an enhancing dura); the automatic segmentation may hold "
                    "the dura, and the answer be millimetres off at the surface");
  }
  if (result.kind == ResultKind::nonrigid)
    if (const std::string caution = refused_rematch_caution(r.report); !caution.empty())
      add_caution(result.metrics, caution);
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

}  // namespace brainshift
