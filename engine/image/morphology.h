#pragma once
// Binary morphology on voxel masks (values 0/1). Ball structuring elements are
// in mm and respect anisotropic spacing: they are computed from exact Euclidean
// distance maps, so cost does not grow with the radius.
// Voxels outside the image are neither foreground nor background: erosion does
// not eat in from the image border.
#include <cstdint>
#include <initializer_list>
#include <vector>

#include "core/image.h"

namespace brainshift {

using Mask = Image3<std::uint8_t>;

Mask mask_of_labels(const LabelImage& labels, std::initializer_list<std::uint16_t> values);
Mask mask_of_labels(const LabelImage& labels, const std::vector<std::uint16_t>& values);
// 1 wherever the label is not 0 (every labelled tissue).
Mask nonzero_mask(const LabelImage& labels);
// 1 where lower <= value <= upper.
Mask threshold(const ImageF& image, float lower, float upper);

// Components numbered 1..count in scan order (x fastest); 0 = background.
// connectivity is 6 or 26 (else InputError). count may be null.
Image3<std::int32_t> connected_components(const Mask& mask, int connectivity, int* count);
// Empty mask in, empty mask out.
Mask largest_component(const Mask& mask, int connectivity);
// Background not 6-connected to the image border becomes foreground.
Mask fill_holes(const Mask& mask);

// The mask's voxels with a 6-neighbour inside the image that is not in the
// mask: its one-voxel inner boundary.
Mask boundary_voxels(const Mask& mask);

// Voxels within radius_mm (centre to centre) of the mask.
Mask dilate(const Mask& mask, double radius_mm);
// Voxels farther than radius_mm from every background voxel.
Mask erode(const Mask& mask, double radius_mm);
Mask close(const Mask& mask, double radius_mm);  // dilate then erode
Mask open(const Mask& mask, double radius_mm);   // erode then dilate

}  // namespace brainshift
