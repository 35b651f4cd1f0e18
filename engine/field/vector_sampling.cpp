#include "field/vector_sampling.h"

#include <algorithm>
#include <array>
#include <cmath>

namespace brainshift {

std::optional<Eigen::Vector3d> sample_vector_linear_voxel(const VectorImage3& field,
                                                          const Eigen::Vector3d& voxel) {
  const auto& dims = field.grid.dims;
  std::array<int, 3> lo{}, hi{};
  std::array<double, 3> t{};
  for (int a = 0; a < 3; ++a) {
    if (!(voxel[a] >= -0.5 && voxel[a] <= dims[a] - 0.5)) return std::nullopt;
    const double c = std::clamp(voxel[a], 0.0, static_cast<double>(dims[a] - 1));
    lo[a] = std::min(static_cast<int>(std::floor(c)), dims[a] - 1);
    hi[a] = std::min(lo[a] + 1, dims[a] - 1);
    t[a] = c - lo[a];
  }
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (int corner = 0; corner < 8; ++corner) {
    const int bx = corner & 1, by = (corner >> 1) & 1, bz = (corner >> 2) & 1;
    const double w = (bx ? t[0] : 1 - t[0]) * (by ? t[1] : 1 - t[1]) * (bz ? t[2] : 1 - t[2]);
    if (w == 0.0) continue;
    const std::size_t v = field.grid.index(bx ? hi[0] : lo[0], by ? hi[1] : lo[1], bz ? hi[2] : lo[2]);
    sum += w * field.vectors[v].cast<double>();
  }
  return sum;
}

std::optional<Eigen::Vector3d> sample_vector_linear(const VectorImage3& field,
                                                    const Eigen::Vector3d& world_mm) {
  const Eigen::Vector3d voxel = (field.grid.voxel_from_world() * world_mm.homogeneous()).head<3>();
  return sample_vector_linear_voxel(field, voxel);
}

}  // namespace brainshift
