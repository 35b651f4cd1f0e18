#pragma once
// A light Potts smoothing of tissue posteriors by mean-field iteration:
//   q_t(x) ~ e_t(x) * exp(beta * sum_n w_n q_t(n))
// over the 6 face neighbours n, each weighted by the smallest spacing over
// its axis' spacing (a neighbour 2.5 mm away across slices says less than
// one 0.9 mm away in plane). e_t: the per-voxel evidence (prior times
// likelihood, any common scale). Jacobi sweeps, a fixed number of them.
#include <array>
#include <vector>

#include "core/image.h"
#include "segmentation/tissue_prior.h"

namespace brainshift::segmentation {

std::array<std::vector<float>, kTissues> potts_mean_field(const std::array<std::vector<float>, kTissues>& evidence,
                                                          const Grid3& grid, double beta, int sweeps);

}  // namespace brainshift::segmentation
