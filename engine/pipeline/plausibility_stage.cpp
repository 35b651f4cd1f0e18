#include "pipeline/plausibility_stage.h"

#include <optional>

#include "image/image_stats.h"
#include "quality/left_right_check.h"

namespace brainshift {
namespace {

double label_volume_ml(const LabelImage& labels, std::uint16_t label) {
  std::size_t n = 0;
  for (auto l : labels.voxels) n += l == label;
  return static_cast<double>(n) * std::abs(labels.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
}

std::string add_all(PlausibilityReport& report, std::vector<GateResult> gates) {
  PlausibilityReport these;
  for (auto& g : gates) {
    these.add(g);
    report.add(std::move(g));
  }
  return these.first_failure();
}

// The structures whose sides the left-right gate compares: the cavities
// (lateral ventricles) and what may be resected (the tumour).
std::vector<std::pair<std::string, std::uint16_t>> asymmetric_structures(const LabelTable& table) {
  std::vector<std::pair<std::string, std::uint16_t>> asymmetric;
  for (const auto& e : table.entries)
    if (e.role == LabelRole::cavity || e.resectable) asymmetric.emplace_back(e.name, e.value);
  return asymmetric;
}

}  // namespace

PlausibilityPreop plausibility_preop(const LabelImage& preop_labels, const LabelTable& table) {
  const auto cavities = table.cavity_labels();
  return {left_right_preop(preop_labels, asymmetric_structures(table)),
          cavities.empty() ? 0.0 : label_volume_ml(preop_labels, cavities.front())};
}

std::string check_input_plausibility(const WarmState& warm, const IntraopInput& input, const Mask& brain_region,
                                     const Eigen::Matrix4d& A, const PipelineParameters& params,
                                     PlausibilityReport& report) {
  const PlausibilityLimits& limits = params.plausibility;
  if (!limits.enabled) return {};
  const LabelTable& table = params.label_table;
  std::vector<GateResult> gates;
  const PreopInView view = preop_in_view(warm.preop.labels, input.labels.grid, A);
  const double in_view = view.fraction;
  GateResult volume = volume_gate(volume_ml(brain_region), in_view * warm.brain_volume_ml, A, limits, input.open_fluid_ml);
  volume.extra["preop_fraction_in_view"] = in_view;
  gates.push_back(std::move(volume));
  std::optional<PlausibilityPreop> own;
  if (!warm.plausibility_preop) own = plausibility_preop(warm.preop.labels, table);
  const PlausibilityPreop& preop = own ? *own : *warm.plausibility_preop;
  const auto cavities = table.cavity_labels();
  if (!cavities.empty())
    gates.push_back(ventricle_volume_gate(label_volume_ml(input.labels, cavities.front()), preop.ventricle_volume_ml,
                                          A, limits));
  for (auto& g : affine_gates(A, limits, [&view](const Eigen::Vector3d& v) { return view.extent_mm(v); },
                              input.open_fluid_ml))
    gates.push_back(std::move(g));
  LeftRightInput lr{warm.preop.labels, input.labels, A, asymmetric_structures(table)};
  lr.preop_side = &preop.left_right;
  if (input.t1) {
    lr.preop_t1 = &warm.preop.t1;
    lr.intraop_t1 = &*input.t1;
    lr.intraop_brain = &brain_region;
  }
  gates.push_back(left_right_gate(lr, limits));
  return add_all(report, std::move(gates));
}

std::string check_field_plausibility(const WarmState& warm, const std::vector<Eigen::Vector3d>& nonrigid_mm,
                                     const PipelineParameters& params, PlausibilityReport& report) {
  if (!params.plausibility.enabled) return {};
  return add_all(report, field_gates(warm.fem.mesh(), nonrigid_mm, params.plausibility));
}

std::string check_image_plausibility(const WarmState& warm, const IntraopInput& input, const Mask& brain_region,
                                     const VectorImage3& pullback_field_mm, const Eigen::Matrix4d& A,
                                     const PipelineParameters& params, PlausibilityReport& report) {
  if (!params.plausibility.enabled) return {};
  if (!input.t1) {
    GateResult untested;
    untested.name = "image";
    untested.tested = false;
    untested.detail = "no intraop image";
    report.add(untested);
    return {};
  }
  return add_all(report, {image_gate(warm.preop.t1, *input.t1, brain_region, pullback_field_mm, A, params.plausibility)});
}

}  // namespace brainshift
