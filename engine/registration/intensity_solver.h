#pragma once
// The intensity refinement's optimisation (registration/intensity_refinement.h):
// Gauss-Newton with iteratively reweighted least squares on the lattice's
// nodes, the bias re-fitted on the way. Internal to the refinement.
#include <vector>

#include "registration/intensity_lattice.h"
#include "registration/intensity_refinement.h"
#include "registration/intensity_samples.h"
#include "registration/linear_sampler.h"

namespace brainshift::intensity {

// The Gauss-Newton loop on the motion samples; returns the iterations done,
// 0 with report->skipped_reason set when the image is not trusted. voxel_mm:
// the intraop image's largest voxel dimension.
int optimise(Lattice& lattice, std::vector<Sample>& motion, const std::vector<Sample>& bias_samples,
             const LinearSampler& preop, const IntensityRefinementParameters& p, double density_per_mm3,
             double voxel_mm, double sigma_floor, IntensityRefinementReport* report);

}  // namespace brainshift::intensity
