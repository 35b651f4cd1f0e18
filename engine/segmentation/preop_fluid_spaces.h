#pragma once
// Given intraop labels made by another segmenter often leave out fluid spaces
// that the preop labels count as brain: the basal cisterns, the third
// ventricle, a wide fissure. Matched as they come, the brain's surface is
// pulled into those pits and the field carries the preop tissue around them
// by several mm (docs/PERFORMANCE.md 12.33: 5-7 mm at landmarks beside the
// suprasellar cistern, where the image alone gave 0.1-1.5 mm). No tissue
// moved there: the space held fluid before the surgery and holds it now.
//
// adopt_preop_fluid_spaces gives such spaces back to the brain, as the preop
// labels define it. A space qualifies when, through the preop placement
// (intraop_from_preop, an affine: deep spaces move by a few mm, less than
// they are wide):
//   - the given labels leave it out and the preop labels call it brain
//     (brain_label only: never a resectable structure, whose cavity is a
//     fluid space made by the surgery);
//   - it is wider than a sulcus or the partial-volume shell a segmenter's
//     threshold leaves around the brain (it survives an opening of
//     min_half_width_mm), so that a shell does not join every space into one;
//   - most of its voxels were fluid in the preop T1 (nearer the preop's fluid
//     median than its tissue median). A sinking's gap fails this test: where
//     it opened, the preop shows the cortex that was there;
//   - when the intraop image is given, each voxel is fluid there too (nearer
//     the given ventricles' median than the given brain's); without
//     ventricles in the given labels that test is off.
// Returns the labels with those spaces set to brain_label and a report.
#include <cstdint>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "core/image.h"

namespace brainshift::segmentation {

struct PreopFluidSpacesInput {
  const LabelImage& given;
  const ImageF* intraop_image;  // on the given labels' grid, or null
  const LabelImage& preop_labels;
  const ImageF& preop_t1;
  Eigen::Matrix4d intraop_from_preop;
  std::uint16_t brain_label;
  std::uint16_t ventricle_label;  // 0: none
  double preop_fluid_median;
  double preop_tissue_median;
};

struct PreopFluidSpacesParameters {
  double min_half_width_mm = 1.5;  // narrower spaces (sulci, a threshold's shell) are left as given
  double min_space_ml = 0.027;     // a body of fluid: at least 27 mm^3 (as the fluid rim's bodies)
};

struct PreopFluidSpaces {
  LabelImage labels;
  double added_ml = 0;
  nlohmann::json report;
};

PreopFluidSpaces adopt_preop_fluid_spaces(const PreopFluidSpacesInput& in, const PreopFluidSpacesParameters& p);

}  // namespace brainshift::segmentation
