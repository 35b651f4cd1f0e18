#pragma once
// Smooth random fields on a grid, shared by the synthetic cases: correlated
// segmentation noise and a coil-like multiplicative bias. Deterministic for a
// given generator state.
#include <random>
#include <vector>

#include "core/image.h"

namespace brainshift {

// Gaussian white noise on a lattice of spacing correlation_mm, interpolated
// trilinearly onto the grid and scaled to rms_mm over it (zeros for rms 0).
std::vector<float> smooth_noise(const Grid3& grid, double correlation_mm, double rms_mm, std::mt19937_64& rng);

// exp(amplitude * g), g a random quadratic polynomial over the grid box with
// max |g| = 1 (ones for amplitude 0).
std::vector<float> bias_field(const Grid3& grid, double amplitude, std::mt19937_64& rng);

}  // namespace brainshift
