#pragma once
// The prepare step of a scan: what the stages need that the scan lacks.
// A scan given as an image alone is segmented here, guided by the preop:
//   1. the preop placed on the image without labels: the head's outline in
//      both images (segmentation/head_mask.h; the skull does not deform) and
//      the label affine (registration/affine_registration.h) between them;
//   2. the preop labels carried through that placement become the prior of
//      the EM classification (segmentation/intraop_segmentation.h);
//   3. the stages run on the segmentation; their non-rigid field carries the
//      preop labels again, with a narrower prior, the image is classified
//      again and re-matched (rematch_rounds times).
// Gates (docs/DESIGN.md "Automatic intraop segmentation"): an image whose
// contrast cannot show the ventricles is refused (InputError); a segmentation
// whose brain volume is far from the preop's, that finds no ventricles, or
// whose outer surface is uncertain over a large area gives the marked
// affine-only result with the reason.
#include <nlohmann/json.hpp>

#include "pipeline/segmentation_gates.h"
#include "pipeline/warm_state.h"

namespace brainshift {

ScanResult register_image_only(WarmState& warm, const ImageF& image, double read_seconds, const PipelineParameters& params,
                               const ProgressFn& progress, bool with_quality_metrics);

// A scan given as labels (with or without its image) that are not checked
// against the image: the stages on them, on the working grid when their grid
// is much finer (pipeline/working_grid.h).
ScanResult register_given_labels(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                 const ProgressFn& progress, bool with_quality_metrics);

}  // namespace brainshift
