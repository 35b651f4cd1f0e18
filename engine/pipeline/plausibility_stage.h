#pragma once
// The plausibility gates (quality/plausibility_gates.h) at their three places
// in the per-scan stages: the input and the affine before the surface match,
// the solved field before it is rasterised, the final field against the
// intraop image. Each returns the reason of the first failed gate (empty when
// all passed) and adds its gates to the report.
#include <string>
#include <vector>

#include <Eigen/Dense>

#include "pipeline/warm_state.h"
#include "quality/plausibility_gates.h"

namespace brainshift {

PlausibilityPreop plausibility_preop(const LabelImage& preop_labels, const LabelTable& table);

std::string check_input_plausibility(const WarmState& warm, const IntraopInput& input, const Mask& brain_region,
                                     const Eigen::Matrix4d& intraop_from_preop, const PipelineParameters& params,
                                     PlausibilityReport& report);
std::string check_field_plausibility(const WarmState& warm, const std::vector<Eigen::Vector3d>& nonrigid_mm,
                                     const PipelineParameters& params, PlausibilityReport& report);
std::string check_image_plausibility(const WarmState& warm, const IntraopInput& input, const Mask& brain_region,
                                     const VectorImage3& pullback_field_mm, const Eigen::Matrix4d& intraop_from_preop,
                                     const PipelineParameters& params, PlausibilityReport& report);

}  // namespace brainshift
