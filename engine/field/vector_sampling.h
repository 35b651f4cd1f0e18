#pragma once
// Trilinear sampling of a displacement field at a world point (RAS+ mm), with
// the inside convention of image/resample.h: a point is inside when its
// continuous voxel coordinate lies in [-0.5, n-0.5] on every axis; within the
// outer half voxel the edge value is replicated.
#include <Eigen/Dense>
#include <optional>

#include "core/image.h"

namespace brainshift {

// std::nullopt outside the field's extent.
std::optional<Eigen::Vector3d> sample_vector_linear(const VectorImage3& field,
                                                    const Eigen::Vector3d& world_mm);

// Same, from a continuous voxel coordinate of the field's grid.
std::optional<Eigen::Vector3d> sample_vector_linear_voxel(const VectorImage3& field,
                                                          const Eigen::Vector3d& voxel);

// The field sampled at every voxel centre of target (trilinear, as above);
// the zero vector where a centre lies beyond the field's extent.
VectorImage3 resample_vector_linear(const VectorImage3& field, const Grid3& target);

}  // namespace brainshift
