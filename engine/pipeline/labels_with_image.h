#pragma once
// A scan given as labels with their image (docs/DESIGN.md "Labels with their
// image"): the labels checked against the image beside their own pass, and,
// unless the push or the configuration says to use them exactly, refined by
// the image as an image-only scan's re-match round is.
#include <nlohmann/json.hpp>

#include "pipeline/given_labels_use.h"
#include "pipeline/warm_state.h"

namespace brainshift {

// A scan given with both labels and an image: the stages run while the labels
// are checked against the image on the other core; a gross disagreement
// (metrics "label_image_check": where and how much) turns the result into
// the marked affine-only one. With GivenLabelsUse::refine the image is then
// classified under the preop the labels' pass carried, and that segmentation
// is registered (result.intraop_labels; metrics "given_labels" says whether,
// or why not).
// Given labels with the fluid spaces the preop counts as brain and they
// leave out given back (segmentation/preop_fluid_spaces.h), placed by their
// own affine: their pass then carries the preop without pulling its surface
// into those pits (docs/DESIGN.md "Given labels and the preop's fluid
// spaces"). The input's labels as they were when none is found; its
// read_seconds grow by this step's time; `report` says what was done. Used for labels an image refines and for labels alone; labels used
// exactly with their image are the site's own word and are left as given.
IntraopInput with_preop_fluid_spaces(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                     nlohmann::json& report);

ScanResult register_labels_with_image(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                      GivenLabelsUse use, const ProgressFn& progress, bool with_quality_metrics);

}  // namespace brainshift
