#include "pipeline/uncertainty_stage.h"

#include <algorithm>
#include <cmath>

#include "core/timer.h"
#include "image/distance_map.h"
#include "protocol/stage_names.h"
#include "quality/uncertainty_map.h"
#include "registration/linear_sampler.h"

namespace brainshift {
namespace {

std::vector<std::uint16_t> tissue_labels(const LabelTable& table) {
  std::vector<std::uint16_t> out;
  for (const auto& e : table.entries)
    if (e.role != LabelRole::cavity && e.value != 0) out.push_back(e.value);
  return out;
}

// Per fixed node: the RMS error of its matched position beyond the
// segmentation's quantisation (which the band adds everywhere): its distance
// to the intraop tissue boundary, what the match could not follow.
std::vector<double> surface_noise_mm(const IntraopInput& input, const std::vector<std::uint16_t>& tissue,
                                     const std::vector<Eigen::Vector3d>& matched_mm) {
  Mask mask(input.labels.grid);
  for (std::size_t v = 0; v < mask.voxels.size(); ++v)
    mask.voxels[v] = std::find(tissue.begin(), tissue.end(), input.labels.voxels[v]) != tissue.end();
  const ImageF sdf = signed_distance_mm(mask);
  const LinearSampler boundary(sdf);
  std::vector<double> sigma(matched_mm.size());
  for (std::size_t i = 0; i < matched_mm.size(); ++i) {
    double d = 0;
    // Outside the grid (field of view cut) the node has no data: its error is
    // as large as the grid's coarsest distance scale allows, 10 voxels.
    if (!boundary.sample(matched_mm[i], &d, nullptr)) d = 10 * input.labels.grid.spacing_mm().maxCoeff();
    sigma[i] = std::abs(d);
  }
  return sigma;
}

// Where the answer places each fixed node on the intraop side (mm), in the
// FEM's fixed-node order: the affine and the node's non-rigid displacement.
std::vector<Eigen::Vector3d> matched_fixed_mm(const WarmState& warm, const ScanResult& result) {
  const auto& fixed = warm.fem.fixed_nodes();
  const auto& nodes = warm.fem.mesh().nodes_mm;
  std::vector<Eigen::Vector3d> out(fixed.size());
  for (std::size_t i = 0; i < fixed.size(); ++i) {
    const int n = fixed[i];
    out[i] = (result.intraop_from_preop * nodes[n].homogeneous()).head<3>();
    if (static_cast<std::size_t>(n) < result.nonrigid_node_mm.size()) out[i] += result.nonrigid_node_mm[n];
  }
  return out;
}

std::vector<Eigen::Vector3d> fixed_preop_mm(const WarmState& warm) {
  std::vector<Eigen::Vector3d> out;
  for (int n : warm.fem.fixed_nodes()) out.push_back(warm.fem.mesh().nodes_mm[n]);
  return out;
}

LinearSolve fem_solve(WarmState& warm) {
  return [&warm](const std::vector<Eigen::Vector3d>& values) {
    std::vector<Eigen::Vector3d> out;
    warm.fem.drive_solve(values, out);
    return out;
  };
}

// Per fixed node: whether the answer places it outside the intraop grid's
// voxel centres, where the scan shows nothing (a field of view that cuts the
// brain: a slab, a short coil). Its position is the model's continuation of
// the seen surface, not a match.
std::vector<bool> unseen_fixed_nodes(const std::vector<Eigen::Vector3d>& matched_mm, const Grid3& grid) {
  const Eigen::Matrix4d voxel_from_world = grid.voxel_from_world();
  std::vector<bool> unseen(matched_mm.size(), false);
  for (std::size_t i = 0; i < matched_mm.size(); ++i) {
    const Eigen::Vector3d v = (voxel_from_world * matched_mm[i].homogeneous()).head<3>();
    for (int a = 0; a < 3; ++a) unseen[i] = unseen[i] || v[a] < 0.0 || v[a] > grid.dims[a] - 1.0;
  }
  return unseen;
}

}  // namespace

void add_uncertainty(WarmState& warm, const IntraopInput& input, const PipelineParameters& params, ScanResult& result,
                     const ProgressFn& progress) {
  if (!params.uncertainty.enabled) return;
  if (progress) progress(std::string(protocol::stages::kUncertainty), 0.0, 0.0);
  Stopwatch watch;
  UncertaintyParameters up = params.uncertainty;
  if (result.kind != ResultKind::nonrigid) up.samples = up.fallback_samples;
  std::vector<double> sigma, node_rms(warm.fem.mesh().node_count(), 0.0);
  const std::vector<Eigen::Vector3d> fixed_preop = fixed_preop_mm(warm), matched = matched_fixed_mm(warm, result);
  if (up.samples > 0) {
    sigma = surface_noise_mm(input, tissue_labels(params.label_table), matched);
    node_rms = propagate_surface_noise(fixed_preop, sigma, fem_solve(warm), up);
  }
  nlohmann::json summary;
  // Brain surface out of view (term 3 of quality/uncertainty_map.h): three
  // warm solves, only when the field of view cuts the brain.
  const std::vector<bool> unseen = unseen_fixed_nodes(matched, input.labels.grid);
  const std::vector<double> unseen_rms = unseen_surface_rms_mm(fixed_preop, unseen, fem_solve(warm), up);
  for (std::size_t n = 0; n < unseen_rms.size() && n < node_rms.size(); ++n)
    node_rms[n] = std::hypot(node_rms[n], unseen_rms[n]);
  summary["unseen_surface"] = {{"fixed_nodes", std::count(unseen.begin(), unseen.end(), true)},
                               {"of", unseen.size()},
                               {"shift_mm", up.unseen_shift_mm}};
  if (!sigma.empty()) {
    double mean_sigma = 0;
    for (double s : sigma) mean_sigma += s / static_cast<double>(sigma.size());
    summary["surface_noise_rms_mm"] = {{"mean", mean_sigma}, {"max", *std::max_element(sigma.begin(), sigma.end())}};
  }
  summary["samples"] = up.samples;
  result.uncertainty_mm = uncertainty_band_mm(
      {warm.fem.mesh(), node_rms, result.pullback_field_mm, result.intraop_from_preop, input.labels,
       result.metrics.contains("refine") && result.metrics["refine"].value("applied", false),
       &result.warped_labels},
      up, &summary);
  summary["meaning"] = "radius (mm) of the 95 % band around each voxel's matched preop point";
  const double seconds = watch.seconds();
  summary["seconds"] = seconds;
  result.metrics["uncertainty"] = std::move(summary);
  result.timings["intraop"]["uncertainty"] = seconds;
  if (progress) progress(std::string(protocol::stages::kUncertainty), 1.0, seconds);
}

}  // namespace brainshift
