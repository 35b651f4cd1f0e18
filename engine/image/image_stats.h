#pragma once
// Small measurements on masks, in voxels and in world units.
#include <Eigen/Dense>
#include <array>
#include <cstddef>

#include "image/morphology.h"

namespace brainshift {

// Inclusive voxel index bounds of the foreground; empty == true when there is none.
struct VoxelBox {
  std::array<int, 3> lo{0, 0, 0};
  std::array<int, 3> hi{-1, -1, -1};
  bool empty = true;
};

VoxelBox bounding_box_voxels(const Mask& mask);
std::size_t count_nonzero(const Mask& mask);
// Voxel count times |det(world_from_voxel)| / 1000 (1 ml = 1000 mm^3).
double volume_ml(const Mask& mask);
// Mean world position (RAS+ mm) of the foreground voxel centres; InputError if empty.
Eigen::Vector3d centroid_mm(const Mask& mask);

}  // namespace brainshift
