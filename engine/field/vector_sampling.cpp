#include "field/vector_sampling.h"

#include "core/parallel.h"
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

VectorImage3 resample_vector_linear(const VectorImage3& field, const Grid3& target) {
  VectorImage3 out(target);
  const Eigen::Matrix4d m = field.grid.voxel_from_world() * target.world_from_voxel;
  // Each output voxel on its own: the slices in two halves side by side.
  parallel_halves(static_cast<std::size_t>(target.dims[2]), 8, [&](std::size_t k0, std::size_t k1) {
    for (auto k = static_cast<int>(k0); k < static_cast<int>(k1); ++k)
      for (int j = 0; j < target.dims[1]; ++j)
        for (int i = 0; i < target.dims[0]; ++i) {
          const auto u = sample_vector_linear_voxel(field, (m * Eigen::Vector4d(i, j, k, 1)).head<3>());
          if (u) out.vectors[target.index(i, j, k)] = u->cast<float>();
        }
  });
  return out;
}

}  // namespace brainshift
