#pragma once
// A scan given as labels with their image (docs/DESIGN.md "Labels with their
// image"): the labels checked against the image beside their own pass, and,
// unless the push or the configuration says to use them exactly, refined by
// the image as an image-only scan's re-match round is.
#include "pipeline/given_labels_use.h"
#include "pipeline/warm_state.h"

namespace brainshift {

// A scan given with both labels and an image: the stages run while the labels
// are checked against the image on the other core. With GivenLabelsUse::refine
// the image is then classified under the preop the labels' pass carried, and
// that segmentation is registered (result.intraop_labels; metrics
// "given_labels" says whether, or why not, and what it changed). Labels the
// check (metrics "label_image_check": where and how much) or the geometry
// gates refuse give, used exactly, the marked affine-only result; to be
// refined, the image's own answer with a caution (metrics "caution").
ScanResult register_labels_with_image(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                      GivenLabelsUse use, const ProgressFn& progress, bool with_quality_metrics);

}  // namespace brainshift
