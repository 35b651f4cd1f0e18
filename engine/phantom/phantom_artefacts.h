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

// The receive sensitivity of an array of `loops` circular surface coils
// (radius loop_radius_mm) on a sphere of radius array_radius_mm round
// centre_mm, the upper part of a head coil (none below 30 % of the radius
// under the centre), turned at random about S-I: each loop's sensitivity
// falls off as a loop's on-axis field, a^3 / (a^2 + r^2)^(3/2) at distance r
// from its centre, and the loops are combined root-sum-of-squares, as an
// array's magnitude image is. Normalised to median 1 over the voxels within
// reference_radius_mm of the centre, then raised to `shading` (0: flat, 1:
// the array's own shading, no intensity normalisation). Not a polynomial:
// bright near the coils, darker in the middle, unlike bias_field, whose
// form the engine's own bias model shares.
std::vector<float> coil_array_bias(const Grid3& grid, const Eigen::Vector3d& centre_mm, int loops,
                                   double array_radius_mm, double loop_radius_mm, double reference_radius_mm,
                                   double shading, std::mt19937_64& rng);

// Magnitude of the value plus complex Gaussian noise of sigma (> 0) per
// component, voxel by voxel in order (one random stream): an MR magnitude
// image's noise, biased upward where the signal is dark.
void add_rician_noise(std::vector<float>& voxels, double sigma, std::mt19937_64& rng);

}  // namespace brainshift
