#pragma once
// Where the EM's classes start (tissue_em.cpp): each tissue's classes from
// the intensities its prior is sure of, the ventricles' from the brain's
// fluid. Internal to the segmentation library.
#include <array>
#include <vector>

#include "segmentation/em_samples.h"
#include "segmentation/tissue_em.h"

namespace brainshift::segmentation {

// Each tissue's classes start from its intensities (no ordering of tissues is
// assumed): one class at their median, several spread evenly over their
// 2-98 % range, so that a rare bright tissue (fat, a T2's fluid) gets a class
// even where a dark one (air) fills most voxels. The ventricles start from
// the brain's fluid (em_initial_classes.cpp fluid_class); the other tissues,
// large enough that a shift leaves most of them in place, from where their
// prior is sure.
std::vector<GaussianClass> initial_classes(const Samples& s, const std::vector<double>& intensity,
                                           const std::array<int, kTissues>& classes_per_tissue,
                                           double ventricle_share);

}  // namespace brainshift::segmentation
