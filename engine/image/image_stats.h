#pragma once
#include <vector>
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
// The box grown by margin_mm on every side (per-axis voxel spacing), clipped
// to the grid.
VoxelBox grow_box(const VoxelBox& box, const Grid3& grid, double margin_mm);
// The voxels of mask inside box as an image of their own, placed at the same
// world position (world_from_voxel shifted to the box's corner): distance maps
// of a small structure then cost its neighbourhood, not the whole grid.
Mask crop_to_box(const Mask& mask, const VoxelBox& box);
std::size_t count_nonzero(const Mask& mask);
// Voxel count times |det(world_from_voxel)| / 1000 (1 ml = 1000 mm^3).
double volume_ml(const Mask& mask);
// Mean world position (RAS+ mm) of the foreground voxel centres; InputError if empty.
Eigen::Vector3d centroid_mm(const Mask& mask);
// The upper median (element size/2 in order) of values, reordering them; 0
// when empty.
float median_in_place(std::vector<float>& values);

}  // namespace brainshift
