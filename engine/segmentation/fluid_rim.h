#pragma once
// The bright fluid rim around the brain in an image whose fluid is the
// brightest tissue (T2-like): peeled off the classified brain from the
// outside in (docs/DESIGN.md "Automatic intraop segmentation", item 11).
#include <vector>

#include "core/image.h"
#include "segmentation/tissue_em.h"

namespace brainshift::segmentation {

// The voxels of `brain` (not `ventricle`) that hold at least half fluid by
// their bias-corrected intensity (image / bias at or beyond the midpoint of
// the fluid class's mean and the cortex's: the major parenchyma class
// nearest the fluid), lie within max_depth_mm of the brain's outside (what
// lies beyond its outline; its enclosed holes are not outside) and reach
// that outside through such voxels (face neighbours). Empty when the fitted
// fluid is not brighter than the largest parenchyma class (not T2-like) or
// max_depth_mm <= 0. All masks, and the bias, on one grid.
// With it, the brain voxels beyond that fluid (caps_beyond_fluid, toward
// centre_voxel): the fluid's partial volume with the bone, darker than half
// fluid, which would otherwise hide the fluid beneath it from the outside.
// A cap is at most max_cap_mm thick (at least max_depth_mm), the fluid it
// hides looked for down to max_depth_mm + max_cap_mm; within cavity_margin_mm
// of `resectable` (empty: nowhere) at most max_depth_mm, and the fluid no
// deeper than max_depth_mm, as beside a cavity the brain lies beyond fluid.
// Below the caps, the rim's depth counts from the outline without them.
// Thick caps also need the fluid class min_separation_sd sd's above the
// cortex's (the sd: the root mean square of the two classes' sd's): they
// judge tissue by being darker than the cortex, which presumes the two are
// told apart (a fit that put the fluid class on the white matter is not).
struct FluidRimBounds {
  double max_depth_mm = 0;
  double max_cap_mm = 0;
  double cavity_margin_mm = 0;
  double min_separation_sd = 0;
};
Mask fluid_rim(const Mask& brain, const Mask& ventricle, const ImageF& image, const std::vector<float>& bias,
               const std::vector<GaussianClass>& classes, const FluidRimBounds& bounds, const Mask& resectable,
               const Eigen::Vector3d& centre_voxel);

}  // namespace brainshift::segmentation
