#pragma once
// Warping preop images into the intraop frame with a pull-back field: the
// output lives on the field's grid and its value at voxel centre x is the preop
// image at x + u(x) (world RAS+ mm; the preop image's own geometry is used, so
// the two grids need not match). Points outside the preop image (its voxels'
// extent, as in image/resample.h) get outside_value. Each splits its slices
// over both cores (core/parallel.h); the result does not depend on it.
#include <cstdint>

#include "core/image.h"

namespace brainshift {

// Trilinear interpolation.
ImageF warp_image_linear(const ImageF& preop, const VectorImage3& pullback, float outside_value = 0.f);
// Nearest neighbour (labels must not be blended).
LabelImage warp_labels_nearest(const LabelImage& preop, const VectorImage3& pullback,
                               std::uint16_t outside_value = 0);

}  // namespace brainshift
