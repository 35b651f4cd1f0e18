#include "field/vector_sampling.h"

#include "image/interpolation.h"

namespace brainshift {

std::optional<Eigen::Vector3d> sample_vector_linear_voxel(const VectorImage3& field,
                                                          const Eigen::Vector3d& voxel) {
  Eigen::Vector3d u;
  if (!trilinear_sample<TrilinearEdge::kVoxelExtent>(field.grid, field.vectors.data(), voxel, &u)) return std::nullopt;
  return u;
}

std::optional<Eigen::Vector3d> sample_vector_linear(const VectorImage3& field,
                                                    const Eigen::Vector3d& world_mm) {
  const Eigen::Vector3d voxel = (field.grid.voxel_from_world() * world_mm.homogeneous()).head<3>();
  return sample_vector_linear_voxel(field, voxel);
}

}  // namespace brainshift
