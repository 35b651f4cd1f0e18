#pragma once
// Given labels (alone, or refined by their image) before their pass: the
// fluid spaces the preop counts as brain given back
// (segmentation/preop_fluid_spaces.h), placed by the labels' own affine.
#include <nlohmann/json.hpp>

#include "pipeline/warm_state.h"

namespace brainshift {

// Given labels with the fluid spaces the preop counts as brain and they
// leave out given back (segmentation/preop_fluid_spaces.h), placed by their
// own affine: their pass then carries the preop without pulling its surface
// into those pits (docs/DESIGN.md "Given labels and the preop's fluid
// spaces"). The input's labels as they were when none is found; its
// read_seconds grow by this step's time; `report` says what was done.
// Used for labels an image refines and for labels alone; labels used
// exactly with their image are the site's own word and are left as given.
IntraopInput with_preop_fluid_spaces(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                     nlohmann::json& report);

}  // namespace brainshift
