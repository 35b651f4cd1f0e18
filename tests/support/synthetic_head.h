#pragma once
// The small synthetic head several test suites share: an ellipsoidal brain
// (label 1, semi-axes 55/65/48 mm) with two lateral ventricles (2) and a
// spherical tumor (4). Coarse enough to mesh in a second.
#include <array>

#include <Eigen/Dense>

#include "core/image.h"

namespace brainshift::test {

struct SyntheticHeadSpec {
  std::array<int, 3> dims{90, 100, 80};
  double spacing_mm = 1.5;
  Eigen::Vector3d origin_mm{-67.5, -75, -60};
  Eigen::Vector3d ventricle_semi_axes_mm{7, 22, 9};
  double tumor_radius_mm = 6;
};

struct SyntheticHead {
  ImageF t1;  // 10 outside, 30 ventricles, 150 tumor, 100 brain
  LabelImage labels;
};

SyntheticHead synthetic_head(const SyntheticHeadSpec& spec = {});

// The synthetic head's image with mild Rician-like noise (sd 3) and a smooth
// bias (+-7 %), as a scanner would give it: an automatic segmentation is
// fitted on the noise, a noiseless image has none.
ImageF scanner_image(const ImageF& clean);

// The preop labels and image carried onto `grid` by a translation of the
// head (intraop = preop + shift_mm); the tumor (4) becomes brain (1), as a
// segmenter without it would label it.
struct MovedHead {
  LabelImage labels;
  ImageF t1;
};
MovedHead move_head(const LabelImage& labels, const ImageF& t1, const Grid3& grid, const Eigen::Vector3d& shift_mm);

// A sinking under a craniotomy at the top: labels above (highest labelled
// z) - depth_mm within radius_mm of the z axis set to 0.
void sink_top(LabelImage& labels, double depth_mm, double radius_mm);

// Dice of the two label maps' outlines (every non-zero label as one), on
// the same grid: how well a segmentation found the head's brain.
double outline_dice(const LabelImage& a, const LabelImage& b);

}  // namespace brainshift::test
