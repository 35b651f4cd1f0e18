#pragma once
// Sampling and resampling through world coordinates (RAS+ mm), never voxel to voxel.
//
// A point is inside an image when its continuous voxel coordinate lies in
// [-0.5, n-0.5] on every axis (the voxels' extent, not only the hull of their
// centres); within the outer half voxel the edge value is replicated. Elsewhere
// outside_value is returned.
#include <Eigen/Dense>
#include <cstdint>

#include "core/image.h"

namespace brainshift {

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

}  // namespace brainshift
