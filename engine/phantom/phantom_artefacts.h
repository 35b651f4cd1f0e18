#pragma once
// Imaging artefacts of the synthetic cases (brain_shift_phantom.h,
// robustness_case.h): correlated segmentation noise, a coil-like
// multiplicative bias and Rician noise. Deterministic for a given generator
// state.
#include <random>
#include <vector>

#include <Eigen/Dense>

#include "core/image.h"
#include "image/gaussian_smooth.h"  // the slice profile of a scanner, the smoothing of a segmenter

namespace brainshift {

// Gaussian white noise on a lattice of spacing correlation_mm, interpolated
// trilinearly onto the grid and scaled to rms_mm over it (zeros for rms 0).
std::vector<float> smooth_noise(const Grid3& grid, double correlation_mm, double rms_mm, std::mt19937_64& rng);

// exp(amplitude * g), g a random quadratic polynomial over the grid box with
// max |g| = 1 (ones for amplitude 0).
std::vector<float> bias_field(const Grid3& grid, double amplitude, std::mt19937_64& rng);

// Magnitude of the value plus complex Gaussian noise of sigma (> 0) per
// component, voxel by voxel in order (one random stream): an MR magnitude
// image's noise, biased upward where the signal is dark.
void add_rician_noise(std::vector<float>& voxels, double sigma, std::mt19937_64& rng);

}  // namespace brainshift
