#pragma once
// Tissue beyond fluid: the brain lies beneath the fluid around it, never
// beyond it. What the classifier calls brain on the far side of a body of
// fluid, between it and the outside and thinner than a cap, is the fluid's
// partial volume with the dura and the bone (docs/DESIGN.md "Automatic
// intraop segmentation", items 7 and 11).
#include <Eigen/Dense>

#include "core/image.h"
#include "image/morphology.h"

namespace brainshift::segmentation {

// The voxels of `brain` (not `ventricle`, not `fluid`) within max_cap_mm of
// `fluid` whose ray toward centre_voxel meets `fluid` before it leaves the
// brain, and whose opposite ray reaches what is neither brain nor fluid (or
// the grid's edge), with less than max_cap_mm of brain on the two rays
// together. `fluid` may lie inside `brain` (the rim not yet peeled) or
// outside it (a gap moved out). The cortex beneath the fluid and gyri rising
// into it look inward into brain and stay.
Mask caps_beyond_fluid(const Mask& brain, const Mask& ventricle, const Mask& fluid, const Eigen::Vector3d& centre_voxel,
                       double max_cap_mm);

}  // namespace brainshift::segmentation
