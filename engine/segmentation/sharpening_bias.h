#pragma once
// A smooth multiplicative bias found without classes, by sharpening the
// brain's intensity histogram (the method of N4, Tustison et al., IEEE TMI
// 2010, with a Gaussian-smoothed field in place of its B-splines):
//   repeat: log intensities corrected by the field so far -> their histogram
//   -> deconvolved by a narrow Gaussian (Wiener) -> each intensity's expected
//   sharpened value -> the residual log(image) - that value, smoothed in
//   space -> added to the field.
// Why before the classes (tissue_em.h): a receive array without intensity
// normalisation shades the brain bright under each loop and dark in the
// middle, a field no low-order polynomial follows, and the classes then take
// the shading for tissue (a parenchyma class per region), after which no
// residual of theirs shows it (docs/PERFORMANCE.md 12.43). The histogram has
// no such freedom: a shading broadens every peak, and only a field that
// varies on the scale of the coils narrows them again. The polynomial bias
// of the classes still fits what is left. Off by default: on real anatomy
// it reads the cortex rim's partial volume as shading (docs/DESIGN.md
// "Automatic intraop segmentation", item 17).
#include <cmath>
#include <cstddef>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "image/morphology.h"

namespace brainshift::segmentation {

struct SharpeningBiasParameters {
  // Lattice the field is estimated on (mm between samples): single voxels,
  // not block means, so that partial volume does not fill the histogram
  // between the tissue peaks.
  double lattice_mm = 4.0;
  // Gaussian sigma (mm) the residual is smoothed with each iteration. A
  // receive loop's sensitivity changes on the scale of its radius and depth
  // (head-array loops are 60-100 mm across, the cortex 20 mm or more from
  // them): a field of 20 mm sigma follows that (30 mm left 3-4x the error).
  // A voxel whose tissue the histogram places has a residual of about 0
  // wherever it lies; partial volume between the peaks does not, and where
  // it is common (the cortex's rim) the field takes some of it.
  double smoothing_mm = 20.0;
  // The histogram's deconvolution: N4's defaults (log units; Wiener noise).
  double fwhm = 0.15;
  double wiener_noise = 0.01;
  int bins = 200;
  // Each iteration's smoothed residual is added this many times over. One
  // sharpening moves every intensity only part of the way to its peak:
  // under a strong array's shading (log rms 0.42: six loops, raised to the
  // power 1.7, on the classifier tests' head) 50 plain iterations left 36 %
  // of it (0.15 in log), twice the step 8 %, and an unshaded image's field
  // stayed at 0.004-0.020 rms (SNR 8-25); four times diverged on an
  // unshaded image (0.045), so 2 keeps a factor of 2 from that
  // (docs/PERFORMANCE.md 12.44).
  double relaxation = 2.0;
  // Bounded: N4's iteration count per level; stops earlier when the field
  // changes by less than `tolerance` (rms, log units) in an iteration.
  int max_iterations = 50;
  double tolerance = 1e-3;
  // Region voxels darker than this fraction of the region's median are air
  // or the noise floor (an open craniotomy's gap), not tissue.
  double floor_fraction = 0.1;
  // The largest |log b| over the brain a coil gives: an unnormalised
  // 8-loop array spans about 4.3-fold (log +-0.73 about its mean); a field
  // past 8-fold found something else and is not used.
  double max_log_bias = std::log(8.0);
  // The smallest region, in lattice samples, a field is estimated from.
  std::size_t min_samples = 500;
};

struct SharpeningBias {
  // log b per voxel of the image's grid (grid order), mean 0 over the region;
  // all 0 when not estimated (too few samples).
  std::vector<float> log_bias;
  int iterations = 0;
  bool converged = false;
  std::size_t samples = 0;
  // Largest |log b| over the region's samples.
  double max_abs_log_bias = 0;
  // Past max_log_bias: log_bias left 0.
  bool discarded = false;
  // rms (log) of what a degree-2 log-polynomial fitted to the field over the
  // samples leaves of it: the shading the classes' own bias cannot follow
  // (the real Colin27 T1: 0.033; an 8-loop array, half and fully
  // unnormalised: 0.07-0.09 and 0.11).
  double beyond_polynomial_rms = 0;
};

// The field on the image's grid from the image's voxels inside `region`
// (same grid): the brain as the prior places it.
SharpeningBias sharpening_log_bias(const ImageF& image, const Mask& region, const SharpeningBiasParameters& p);

nlohmann::json to_json(const SharpeningBias& b);

}  // namespace brainshift::segmentation
