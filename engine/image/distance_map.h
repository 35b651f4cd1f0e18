#pragma once
// Exact Euclidean distance maps in mm on (possibly anisotropic) voxel grids:
// separable lower-envelope-of-parabolas algorithm (Felzenszwalb & Huttenlocher
// 2012), O(N). Distances are between voxel centres, using the grid's spacing
// (column norms of world_from_voxel; shear is ignored).
#include "core/image.h"
#include "image/morphology.h"

namespace brainshift {

// 0 inside the mask; outside, distance to the nearest mask voxel centre.
// +infinity everywhere when the mask is empty.
ImageF distance_to_mask_mm(const Mask& mask);

// The same up to cap_mm (exact there), +infinity beyond: for a caller that
// needs the distance only that far.
ImageF distance_to_mask_mm(const Mask& mask, double cap_mm);

// Squared distances (mm^2), the same map before the square root; useful for
// thresholding without sqrt rounding.
ImageF squared_distance_to_mask_mm2(const Mask& mask);

// The same up to cap_mm2 (exact there); +infinity where it exceeds the cap.
// For thresholds at or below the cap, at a fraction of the cost far from the
// mask.
ImageF squared_distance_to_mask_mm2(const Mask& mask, double cap_mm2);

// Negative inside, positive outside. With d_out = distance to the nearest mask
// voxel and d_in = distance to the nearest background voxel:
//   outside: d_out - h/2,   inside: -(d_in - h/2),   h = smallest voxel spacing.
// The half voxel makes |value| approximate the distance to the voxelised surface
// (the faces between mask and background voxels), and because the offset is
// symmetric the zero level of a linear interpolation lies halfway between
// neighbouring boundary voxels. Along a coarser axis the error is at most
// (h_axis - h)/2. Empty mask: +inf everywhere; full mask: -inf everywhere.
ImageF signed_distance_mm(const Mask& mask);

}  // namespace brainshift
