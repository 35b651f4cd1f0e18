#pragma once
// Does a given intraop segmentation agree with its own image? The image is
// classified with the segmentation itself as a wide prior (tissue_em.h): where
// the image clearly shows fluid, dura or air, the classification says so
// whatever the labels claim, and where it clearly shows brain outside them,
// that too. Disagreement within a band of partial volume and ordinary
// segmentation noise (band_mm) is expected; beyond it, a volume of it is a
// leak into fluid or dura (labels say brain, the image does not), a missing
// lobe (the image shows brain the labels lack), or labels that do not belong
// to this image (mirrored, shifted, another patient's).
#include <array>
#include <cstddef>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "segmentation/intraop_segmentation.h"

namespace brainshift::segmentation {

struct LabelImageCheckParameters {
  SegmentationParameters classifier;  // prior_width_mm and em.fit_samples set by the check
  // Width of the prior around the given outline: wide enough that a
  // several-mm leak is decided by the image, not by the labels.
  double prior_width_mm = 4.0;
  // Disagreement counts only where the image's choice is this sure and farther
  // than band_mm from the image's own brain surface: partial volume (half a
  // voxel), boundary noise of a careful segmentation (a voxel or two) and the
  // slice thickness of intraop scans (up to 3 mm) stay inside 3 mm.
  double min_posterior = 0.9;
  double band_mm = 3.0;
  // Gross: beyond the band, more than this fraction of the brain's volume
  // (2 %, about 25 ml: a 45 mm block is 90 ml, a 4 mm leak over a third of
  // the surface some 100 ml; physiological brain shift moves no tissue out of
  // the image's brain).
  double max_disagreement_fraction = 0.02;
  // The check classifies on the working grid of this spacing (image/
  // resample.h: never finer than the image's own, the labels taken by
  // cover): distances beyond the band are counted in whole voxels,
  // and at 2 mm the first depth counted beyond band_mm (4 mm) is the same
  // as at 1 mm, while the classification costs a quarter to an eighth
  // (docs/DESIGN.md "The labels-vs-image check's grid"). 0: the image's grid.
  double grid_spacing_mm = 2.0;
  // The classifier's parameters are fitted on this many voxels (its EM
  // iterations cost in proportion): 20 000 still give the ventricles, the
  // smallest tissue in the box (about 0.5 %), some 100 samples, a class mean
  // to a tenth of its sd, far below what moves an outline by 3 mm.
  std::size_t fit_samples = 20000;
};

struct Disagreement {
  double volume_ml = 0;      // beyond the band
  double max_depth_mm = 0;   // farthest from the image's brain surface
  std::array<double, 3> centroid_mm{0, 0, 0};  // where (RAS)
};

struct LabelImageCheck {
  Disagreement labels_not_image;  // labelled brain the image shows as fluid, dura, air (a leak)
  Disagreement image_not_labels;  // brain in the image the labels lack (a missing lobe)
  double brain_ml = 0;
  std::string failure;  // why the labels cannot be trusted with this image; empty when they can
  nlohmann::json metrics;
};

// Voxels of `a` not in `b` that a classification chose surely (its
// confidence at least min_posterior), farther than band_mm outside b's
// surface: the check's measure of disagreement, also used to say what the
// image's refinement changed in given labels (pipeline/labels_with_image.cpp).
Disagreement disagreement_beyond_band(const Mask& a, const Mask& b, const ImageF& confidence, double min_posterior,
                                      double band_mm);
nlohmann::json to_json(const Disagreement& d);
// "V ml beyond B mm, up to D mm deep, centred at (x, y, z) mm RAS".
std::string to_text(const Disagreement& d, double band_mm);

// labels in the table's values on the image's grid. The volumes, depths and
// centroid are measured on the check's grid (grid_spacing_mm).
LabelImageCheck check_labels_against_image(const ImageF& image, const LabelImage& labels, std::uint16_t brain_label,
                                           const std::vector<std::uint16_t>& ventricle_labels,
                                           const LabelImageCheckParameters& params);

}  // namespace brainshift::segmentation
