#pragma once
// Separable Gaussian smoothing of a scalar image along its voxel axes.
#include <Eigen/Dense>

#include "core/image.h"

namespace brainshift {

// sigma per axis in voxels (an axis with sigma below 0.05 is left alone);
// edges replicated. Used for a scanner's slice profile and a segmenter's
// smoothing (phantom), and to bring the preop T1 to an intraop scanner's
// resolution (registration/intensity_refinement.h).
void gaussian_smooth_voxels(ImageF& image, const Eigen::Vector3d& sigma_voxels);

}  // namespace brainshift
