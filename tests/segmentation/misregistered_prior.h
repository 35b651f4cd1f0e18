#pragma once
// The prior the classifier tests give: a truth label map moved by shift_mm
// and scaled about the world origin (nearest neighbour), the misregistration
// the classifier must see through.
#include <cmath>

#include <Eigen/Dense>

#include "core/image.h"

namespace brainshift::segmentation::test_support {

inline LabelImage misregistered(const LabelImage& truth, const Eigen::Vector3d& shift_mm, double scale) {
  LabelImage out(truth.grid, 0);
  const Eigen::Matrix4d vfw = truth.grid.voxel_from_world();
  for (int k = 0; k < truth.grid.dims[2]; ++k)
    for (int j = 0; j < truth.grid.dims[1]; ++j)
      for (int i = 0; i < truth.grid.dims[0]; ++i) {
        const Eigen::Vector3d src = (truth.grid.world_mm(i, j, k) - shift_mm) / scale;
        const Eigen::Vector3d v = (vfw * src.homogeneous()).head<3>();
        const int a = static_cast<int>(std::lround(v.x())), b = static_cast<int>(std::lround(v.y())),
                  c = static_cast<int>(std::lround(v.z()));
        if (truth.grid.contains(a, b, c)) out.at(i, j, k) = truth.at(a, b, c);
      }
  return out;
}

}  // namespace brainshift::segmentation::test_support
