#pragma once
// The uncertainty map of a served scan (quality/uncertainty_map.h), computed
// after the answer is out: the surface residuals measured against the intraop
// labels, their noise propagated through the warm factorisation, the map
// written to result.uncertainty_mm and summarised in metrics.uncertainty.
#include "pipeline/warm_state.h"

namespace brainshift {

void add_uncertainty(WarmState& warm, const IntraopInput& input, const PipelineParameters& params, ScanResult& result,
                     const ProgressFn& progress);

}  // namespace brainshift
