#pragma once
// The EM's fit sample (tissue_em.cpp): the fit's parameters are estimated on
// a regular lattice of voxels, each with its intensity and the prior's say
// about it; the posterior is then computed on every voxel. Internal to the
// segmentation library.
#include <array>
#include <cstddef>
#include <vector>

#include "core/image.h"
#include "segmentation/tissue_prior.h"

namespace brainshift::segmentation {

// The log of a prior of 0 (a tissue the prior rules out there).
constexpr double kLogTiny = -1e30;

struct Samples {
  std::vector<std::array<int, 3>> voxel;
  std::vector<double> intensity;                 // normalised
  std::vector<std::array<double, kTissues>> log_prior;
  std::vector<char> band;  // in_surface_band
  std::vector<double> inside;  // prior of brain (parenchyma + ventricles), for the bias step
};

// The prior's brain (parenchyma + ventricles) at voxel v.
inline double brain_prior_at(const TissuePrior& prior, std::size_t v) {
  return static_cast<double>(prior.p[index_of(Tissue::parenchyma)][v]) + prior.p[index_of(Tissue::ventricle)][v];
}

// A regular subsample of at most `budget` voxels of image (intensities over
// `scale`) with their prior: see sample_strides in em_samples.cpp.
Samples draw_samples(const ImageF& image, const TissuePrior& prior, double scale, std::size_t budget);

// The 99th percentile of the image inside the prior's brain (the fit's
// intensity unit). InputError when the prior places no brain in the image or
// the image is not positive there.
double brain_intensity_scale(const ImageF& image, const TissuePrior& prior);

}  // namespace brainshift::segmentation
