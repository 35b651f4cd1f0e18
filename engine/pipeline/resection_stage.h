#pragma once
// Resection. A structure marked resectable (the tumor) has its wall meshed and
// a system of its own in which that wall is fixed too. When the intraop scan
// shows a cavity where the first solve put the structure (non-tissue voxels
// enclosed by the brain next to it, or inside its wall even when the cavity
// is open to the surface through the surgical corridor),
// its wall is matched to the cavity (like a ventricle wall) and the elastic
// problem is solved again in that system: the tissue around the cavity then
// follows its collapse instead of being held by nothing: with the cavity
// ignored, no boundary condition reaches the tissue next to it (docs/DESIGN.md,
// "Resection").
#include <Eigen/Dense>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "image/morphology.h"
#include "pipeline/warm_state.h"

namespace brainshift {

struct ResectionMatch {
  int system = 0;                                // 0: no resection found or matched
  std::vector<Eigen::Vector3d> fixed_values_mm;  // follows fem.fixed_nodes(system)
  nlohmann::json metrics;
};

// intraop_from_preop: the affine; nonrigid_mm: every node's displacement from
// the system-0 solve; fixed_values_mm: its boundary values (fixed_nodes(0)).
// Never fails the scan: a wall match that folds, crosses itself or does not
// reach the cavity is reported in the metrics and the system-0 result stands.
ResectionMatch match_resection(const WarmState& warm, const IntraopInput& input, const Mask& brain_region,
                               const Eigen::Matrix4d& intraop_from_preop,
                               const std::vector<Eigen::Vector3d>& nonrigid_mm,
                               const std::vector<Eigen::Vector3d>& fixed_values_mm,
                               const PipelineParameters& params);

}  // namespace brainshift
