#pragma once
// Sampling and resampling through world coordinates (RAS+ mm), never voxel to voxel.
//
// A point is inside an image when its continuous voxel coordinate lies in
// [-0.5, n-0.5] on every axis (the voxels' extent, not only the hull of their
// centres); within the outer half voxel the edge value is replicated. Elsewhere
// outside_value is returned. (TrilinearEdge::kVoxelExtent of image/interpolation.h.)
#include <Eigen/Dense>
#include <array>
#include <cstdint>
#include <vector>

#include "core/image.h"
#include "image/interpolation.h"

namespace brainshift {

// Samples voxel data on one grid at many world points, with the inverse
// affine computed once (sample_linear inverts it on every call).
class GridSampler {
 public:
  explicit GridSampler(const Grid3& grid) : grid_(grid), voxel_from_world_(grid.voxel_from_world()) {}
  Eigen::Vector3d voxel(const Eigen::Vector3d& world_mm) const {
    return (voxel_from_world_ * world_mm.homogeneous()).head<3>();
  }
  // voxels: grid.voxel_count() values in grid order.
  float linear(const std::vector<float>& voxels, const Eigen::Vector3d& world_mm, float outside_value) const {
    double value;
    return trilinear_sample<TrilinearEdge::kVoxelExtent>(grid_, voxels.data(), voxel(world_mm), &value)
               ? static_cast<float>(value)
               : outside_value;
  }
  std::uint16_t nearest(const std::vector<std::uint16_t>& voxels, const Eigen::Vector3d& world_mm,
                        std::uint16_t outside_value) const {
    std::size_t index;
    return nearest_voxel(grid_, voxel(world_mm), &index) ? voxels[index] : outside_value;
  }

 private:
  Grid3 grid_;
  Eigen::Matrix4d voxel_from_world_;
};

float sample_linear(const ImageF& image, const Eigen::Vector3d& world_mm, float outside_value);
std::uint16_t sample_nearest(const LabelImage& labels, const Eigen::Vector3d& world_mm,
                             std::uint16_t outside_value);

// Value at target voxel centre x is src(src_world_from_target_world * world(x)).
ImageF resample_linear(const ImageF& src, const Grid3& target,
                       const Eigen::Matrix4d& src_world_from_target_world = Eigen::Matrix4d::Identity(),
                       float outside_value = 0.f);
LabelImage resample_nearest(const LabelImage& src, const Grid3& target,
                            const Eigen::Matrix4d& src_world_from_target_world = Eigen::Matrix4d::Identity(),
                            std::uint16_t outside_value = 0);

// The grid spanning the same box in world as `grid` (the extent of its
// voxels, not only their centres) with `dims` voxels along its axes (same
// directions).
Grid3 same_extent_grid(const Grid3& grid, const std::array<int, 3>& dims);

// An axis is coarsened only when its spacing is below working_spacing_mm by
// more than this factor: a smaller change saves little (under a fifth of the
// voxels along that axis) while the smoothing blurs the partial volume the
// classifier reads; scans at 0.94-1 mm, as validated, are worked on as they
// are.
inline constexpr double kWorkingGridMinCoarsening = 1.25;

// The image's grid, or the grid of the same extent and axes whose spacing is
// working_spacing_mm (to a whole number of voxels) along each axis finer than
// working_spacing_mm / kWorkingGridMinCoarsening. working_spacing_mm 0: the
// image's grid.
Grid3 working_grid(const Grid3& image_grid, double working_spacing_mm);

// image on a grid of coarser (or equal) spacing: smoothed to the coarser
// voxels' profile first, then sampled linearly.
ImageF downsample_linear(const ImageF& image, const Grid3& coarser);

// labels on a coarser grid of the same extent (same_extent_grid of theirs):
// each coarser voxel takes the label covering most of its box (the source
// voxels' overlaps with it, per axis). The nearest source voxel to a coarser
// centre is no rule for a whole ratio: at 2:1 every centre falls halfway
// between two source voxels, and rounding the halves one way moves every
// outline by half a source voxel along each axis. An exact tie alternates
// between the tied labels in a checkerboard, so that no direction is
// favoured. Throws std::invalid_argument for a grid of another extent.
LabelImage downsample_labels(const LabelImage& labels, const Grid3& coarser);

}  // namespace brainshift
