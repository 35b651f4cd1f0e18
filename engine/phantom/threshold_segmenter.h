#pragma once
// An intraop segmentation made by an ALGORITHM from the scanner's image, as a
// site without a hand segmentation would make it (never by perturbing the
// truth): its errors come from the algorithm meeting the image.
//   1. Gaussian smoothing (smoothing_mm).
//   2. Four-class Otsu on the histogram of the whole image. T1: air | bone
//      and CSF | grey matter | white matter and fat; brain = at least the
//      second threshold. T2-like: air and bone | white | grey | CSF; brain =
//      from the first threshold to below the third.
//   3. Within a region of interest: the expected brain (e.g. the preop
//      brain moved by a rigid registration) dilated by roi_margin_mm, which
//      keeps the threshold out of the neck and the orbits as an
//      atlas-guided site pipeline does.
//   4. Morphology: opening (cuts thin bridges to the scalp), the largest
//      6-connected component, hole filling in each slice (the ventricles
//      are open to the cisterns in 3D, not within a slice), closing, hole
//      filling in 3D.
//   5. Ventricles: CSF voxels (T1 below the lower threshold, T2 above the
//      upper) of the brain eroded by ventricle_margin_mm and within
//      ventricle_roi_margin_mm of the expected ventricles, grown
//      (6-connected) from the CSF voxel nearest to each expected ventricle
//      point within seed_search_mm (e.g. the preop ventricles moved by a
//      rigid registration).
// Typical errors, by construction: partial-volume erosion at thick slices,
// thin horns lost, a hypointense tumour at the surface dropped from the T1
// brain mask, blood in a cavity counted as brain, a T2-like mask that takes
// partial-volume CSF.
#include <Eigen/Dense>
#include <cstdint>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "image/morphology.h"
#include "phantom/scanner_model.h"

namespace brainshift {

struct ThresholdSegmenterSpec {
  Contrast contrast = Contrast::t1;  // dark or bright CSF
  double smoothing_mm = 1.0;
  double opening_mm = 3.0;
  double closing_mm = 2.0;
  double ventricle_margin_mm = 3.0;
  // The brain may move outward past its preop outline by swelling (2-4 mm in
  // the suites) and a rigid pre-registration's error (about a millimetre):
  // 5 mm keeps it, and keeps out the neck and orbits, a centimetre away.
  double roi_margin_mm = 5.0;
  // The ventricles move with the deep part of the sinking (2-5 mm) or a
  // midline shift (up to 6 mm); growth farther than 8 mm from where they
  // were is a leak into other CSF (third ventricle, cisterns).
  double ventricle_roi_margin_mm = 8.0;
  double seed_search_mm = 12.0;
  std::uint16_t brain_label = 1;      // the label table's values
  std::uint16_t ventricle_label = 2;
};

struct ThresholdSegmentation {
  LabelImage labels;            // on the image's grid: 0, brain_label, ventricle_label
  nlohmann::json description;   // thresholds, seeds found, volumes
};

// InputError on an empty image or a bad spec. No seed found: no ventricles
// (reported in the description), as such a segmenter would return.
// What the segmenter expects (e.g. the preop moved rigidly): masks on the
// image's grid, or null for no region of interest.
struct SegmenterPrior {
  std::vector<Eigen::Vector3d> ventricle_points_mm;
  const Mask* brain = nullptr;
  const Mask* ventricles = nullptr;
};
ThresholdSegmentation segment_by_threshold(const ImageF& image, const SegmenterPrior& prior,
                                           const ThresholdSegmenterSpec& spec);

// Background not 4-connected to its slice's border (slices along the third
// voxel axis) becomes foreground.
Mask fill_holes_per_slice(const Mask& mask);

// The classes-1 thresholds (ascending) of a multi-class Otsu split of the
// values (128 bins between the 0.1 and 99.9 percentiles, exact by dynamic
// programming). InputError for classes outside 2-8 or too few values.
std::vector<double> otsu_thresholds(const std::vector<float>& values, int classes);

}  // namespace brainshift
