#pragma once
// Smooth extension of a vector field known on part of a voxel grid to the rest
// (used for the non-rigid remainder outside the deformed mesh). Internal to the
// field module but exposed for testing.
#include <Eigen/Dense>
#include <cstdint>
#include <vector>

#include "core/image.h"

namespace brainshift {

// Push-pull pyramid inpainting (Gortler et al. 1996): weighted averages are
// pushed down a pyramid (2x per axis, but an axis is only halved while its
// spacing is <= 1.5x the finest one, so levels stay roughly isotropic in mm),
// then pulled up with trilinear upsampling into the voxels with known == 0.
// Known voxels are left untouched. With no known voxel at all, values become 0.
// Only the voxels listed in `targets` are written at the finest level (the
// others keep their values): callers list the voxels they will use.
void fill_push_pull(const Grid3& grid, const std::vector<std::uint8_t>& known,
                    const std::vector<std::uint32_t>& targets, std::vector<Eigen::Vector3f>& values);

// Red-black Gauss-Seidel sweeps of the (spacing-weighted, 6-neighbour) Laplace equation on
// the voxels listed in `free_voxels`; every other voxel acts as a fixed value.
// Removes the blockiness of the pyramid and makes the extension meet the known
// values continuously.
void relax_laplace(const Grid3& grid, const std::vector<std::uint32_t>& free_voxels,
                   int sweeps, std::vector<Eigen::Vector3f>& values);

}  // namespace brainshift
