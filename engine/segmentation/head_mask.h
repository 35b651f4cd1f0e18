#pragma once
// The head in an MR image without any labels: what separates the scanner's
// air from tissue in every MR contrast (air gives no signal), so a T1, a T2 or
// a bias-ridden low-field image give the same head. Used to place the preop
// labels roughly on an intraop image before anything is segmented: the skull
// does not deform, so the head's outline carries the rigid positioning of the
// patient, and the brain's shift is left to the classification.
#include "core/image.h"
#include "image/morphology.h"

namespace brainshift::segmentation {

// Otsu's threshold between air and tissue on the image's histogram, the
// largest 6-connected component, closed by closing_mm (bridges the dark
// skull and sinus gaps a threshold leaves in the scalp) and holes filled.
// Computed on a grid of about coarse_mm spacing (the head's outline to a few
// mm is all an initial alignment needs). Empty mask when the image is flat.
Mask head_mask(const ImageF& image, double coarse_mm = 3.0, double closing_mm = 6.0);

// Otsu (1979): the threshold maximising the between-class variance of the
// histogram (256 bins over [min, max]).
float otsu_threshold(const std::vector<float>& values);

}  // namespace brainshift::segmentation
