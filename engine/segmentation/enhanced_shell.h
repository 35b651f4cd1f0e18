#pragma once
// Does a bright shell hug the segmented brain? On a T1 made without
// contrast, what lies 1.5-3 mm outside the brain's outline is the
// subarachnoid CSF, the dura and the skull's inner table, all dark (the
// suite's unenhanced scans: 1-4 % of those voxels as bright as 0.8 of the
// brain's median); after gadolinium the dura enhances (17-31 % there), and
// where it lies on the cortex the classifier cannot part it from the brain
// (docs/DESIGN.md "Automatic intraop segmentation", item 13); where it
// took the dura in, the outline's outer layer is as bright as the cortex
// beneath. Measured, not corrected: the answer is cautioned. Not tested on a bright-fluid image
// (T2-like), whose CSF rim is bright by nature.
#include <string>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "segmentation/tissue_em.h"

namespace brainshift::segmentation {

struct EnhancedShellParameters {
  double inner_mm = 1.5;  // beyond the outline's partial volume (a voxel)
  double outer_mm = 3.0;  // before the diploe's fat (the inner table and dura are 2-4 mm thick together)
  double bright_fraction_of_brain_median = 0.8;  // brighter than the CSF/bone partial volume, as bright as cortex
  // Above this share of the shell's voxels bright, the image is taken as
  // enhanced: 2.5 x the most seen on an unenhanced scan of the suite, 0.6 x
  // the least on an enhanced one (docs/PERFORMANCE.md 12.36).
  double max_bright_fraction = 0.10;
  // Where the segmentation took most of the dura in, less lies bright beyond
  // it, but the outline's outer layer is as bright as the layer beneath
  // (surface_ratio): both signs at once, each weaker, also caution. The
  // cortex's outer layer, grey matter in partial volume with the CSF, is
  // darker than the layer beneath on every unenhanced T1 measured (0.855-
  // 0.902 on 94 suite answers, 0.875 on the real Colin27 T1); a dura taken
  // in raised it to 0.952-1.024: the limit lies between. The ratio alone is
  // no proof (the pipeline tests' smooth synthetic cortex: 0.989, an
  // infant's white matter darker than its grey would be another), so the
  // bright share beyond must also exceed what unenhanced scans show (at
  // most 0.046 on the 68 the limit was set from; one of family 17's later
  // reached 0.054 with a ratio of 0.862, and only the conjunction kept it
  // quiet) against 0.061-0.085 on the enhanced scans the first test
  // missed. docs/PERFORMANCE.md 12.37.
  double outline_surface_ratio = 0.93;
  double outline_bright_fraction = 0.05;
};

struct EnhancedShell {
  bool tested = false;
  double bright_fraction = 0;  // of the shell's voxels in the image
  // The outline's outer layer's mean over the layer beneath's (a voxel, at
  // least inner_mm, each): judged only with the bright share beyond
  // (EnhancedShellParameters::outline_surface_ratio).
  double surface_ratio = 0;
  bool enhanced = false;
  std::string why_not_tested;
  nlohmann::json metrics;
};

// image and bias (multiplicative) on brain's grid; brain is the outline
// (holes filled). classes: the segmentation's fitted classes.
EnhancedShell enhanced_shell(const ImageF& image, const ImageF& bias, const Mask& brain,
                             const std::vector<GaussianClass>& classes, const EnhancedShellParameters& params = {});

}  // namespace brainshift::segmentation
