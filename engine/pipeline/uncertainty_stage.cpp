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
std::vector<double> surface_noise_mm(const WarmState& warm, const IntraopInput& input,
                                     const std::vector<std::uint16_t>& tissue, const ScanResult& result) {
  Mask mask(input.labels.grid);
  for (std::size_t v = 0; v < mask.voxels.size(); ++v)
    mask.voxels[v] = std::find(tissue.begin(), tissue.end(), input.labels.voxels[v]) != tissue.end();
  const ImageF sdf = signed_distance_mm(mask);
  const LinearSampler boundary(sdf);
  const auto& fixed = warm.fem.fixed_nodes();
  const auto& nodes = warm.fem.mesh().nodes_mm;
  std::vector<double> sigma(fixed.size());
  for (std::size_t i = 0; i < fixed.size(); ++i) {
    const int n = fixed[i];
    Eigen::Vector3d q = (result.intraop_from_preop * nodes[n].homogeneous()).head<3>();
    if (static_cast<std::size_t>(n) < result.nonrigid_node_mm.size()) q += result.nonrigid_node_mm[n];
    double d = 0;
    // Outside the grid (field of view cut) the node has no data: its error is
    // as large as the grid's coarsest distance scale allows, 10 voxels.
    if (!boundary.sample(q, &d, nullptr)) d = 10 * input.labels.grid.spacing_mm().maxCoeff();
    sigma[i] = std::abs(d);
  }
  return sigma;
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
  if (up.samples > 0) {
    sigma = surface_noise_mm(warm, input, tissue_labels(params.label_table), result);
    std::vector<Eigen::Vector3d> fixed_preop;
    for (int n : warm.fem.fixed_nodes()) fixed_preop.push_back(warm.fem.mesh().nodes_mm[n]);
    const LinearSolve solve = [&warm](const std::vector<Eigen::Vector3d>& values) {
      std::vector<Eigen::Vector3d> out;
      warm.fem.drive_solve(values, out);
      return out;
    };
    node_rms = propagate_surface_noise(fixed_preop, sigma, solve, up);
  }
  nlohmann::json summary;
  if (!sigma.empty()) {
    double mean_sigma = 0;
    for (double s : sigma) mean_sigma += s / static_cast<double>(sigma.size());
    summary["surface_noise_rms_mm"] = {{"mean", mean_sigma}, {"max", *std::max_element(sigma.begin(), sigma.end())}};
  }
  summary["samples"] = up.samples;
  result.uncertainty_mm = uncertainty_band_mm(
      {warm.fem.mesh(), node_rms, result.pullback_field_mm, result.intraop_from_preop, input.labels,
       result.metrics.contains("refine") && result.metrics["refine"].value("applied", false)},
      up, &summary);
  summary["meaning"] = "radius (mm) of the 95 % band around each voxel's matched preop point";
  const double seconds = watch.seconds();
  summary["seconds"] = seconds;
  result.metrics["uncertainty"] = std::move(summary);
  result.timings["intraop"]["uncertainty"] = seconds;
  if (progress) progress(std::string(protocol::stages::kUncertainty), 1.0, seconds);
}

}  // namespace brainshift
