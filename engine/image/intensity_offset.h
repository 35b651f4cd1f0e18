#pragma once
// An MR magnitude image is non-negative, its air near zero; the classifier's
// multiplicative bias, its head mask and the intensity refinement rely on
// that. An image with negative values has been shifted on its way here (a
// stored intercept of -1024, a z-scored export from an image pipeline): a
// z-scored intraop T1 was refused as "the field of view misses most of the
// brain" before this (docs/performance/12.45). Lifting it back puts air near
// zero again; an image without negative values is left as it is (a positive
// pedestal is not detected).
#include "core/image.h"

namespace brainshift {

// The value the image is lifted by: its 0.1st percentile (a strided sample),
// negated; values still below zero then are clamped to zero. Air fills a large
// part of any head scan's field of view, so that percentile lies in the air's
// noise, not in tissue; the lowest value itself would follow one outlier.
inline constexpr double kIntensityFloorPercentile = 0.001;

bool has_negative_intensities(const ImageF& image);

// Lifts the image when it holds a negative value; returns the amount added
// (0: unchanged, or only a few negative outliers clamped at zero).
double lift_negative_intensities(ImageF& image);

}  // namespace brainshift
