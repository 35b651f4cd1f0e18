#include "segmentation/fluid_caps.h"

#include <array>
#include <cmath>
#include <vector>

#include "core/parallel.h"

namespace brainshift::segmentation {

Mask caps_beyond_fluid(const Mask& brain, const Mask& ventricle, const Mask& fluid, const Eigen::Vector3d& centre_voxel,
                       double max_cap_mm) {
  const Grid3& g = brain.grid;
  const Eigen::Vector3d spacing = g.spacing_mm();
  const double step_mm = 0.5 * spacing.minCoeff();
  const int steps = static_cast<int>(std::ceil(max_cap_mm / step_mm));
  const Mask candidates = dilate(fluid, max_cap_mm);
  // Steps along dir (voxels per step) until the ray leaves brain tissue for
  // what `stop` marks (or the grid); -1 when it does not within `limit`.
  const auto run = [&](const Eigen::Vector3d& p, const Eigen::Vector3d& dir, int limit, const auto& stop) {
    for (int s = 1; s <= limit; ++s) {
      const Eigen::Vector3d q = p + s * dir;
      const int a = static_cast<int>(std::lround(q.x())), b = static_cast<int>(std::lround(q.y())),
                c = static_cast<int>(std::lround(q.z()));
      if (!g.contains(a, b, c)) return s;
      if (stop(g.index(a, b, c))) return s;
      if (!brain.at(a, b, c) && !fluid.at(a, b, c)) return -1;  // another way out of the brain
    }
    return -1;
  };
  std::vector<std::array<int, 3>> rays;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        if (brain.voxels[v] && !ventricle.voxels[v] && !fluid.voxels[v] && candidates.voxels[v]) rays.push_back({i, j, k});
      }
  // Each ray reads the masks and writes its own voxel: the two halves of the
  // list side by side, the same voxels either way.
  Mask beyond(g, 0);
  parallel_halves(rays.size(), 4096, [&](std::size_t begin, std::size_t end) {
    for (std::size_t r = begin; r < end; ++r) {
      const auto [i, j, k] = rays[r];
      const Eigen::Vector3d p(i, j, k);
      const Eigen::Vector3d to_centre = centre_voxel - p;
      const double length_mm = to_centre.cwiseProduct(spacing).norm();
      if (length_mm < step_mm) continue;
      const Eigen::Vector3d dir = to_centre * (step_mm / length_mm);
      const int in = run(p, dir, steps, [&](std::size_t u) { return fluid.voxels[u] != 0; });
      if (in < 0) continue;
      const int out = run(p, -dir, steps - in, [&](std::size_t u) { return !brain.voxels[u] && !fluid.voxels[u]; });
      if (out >= 0) beyond.voxels[g.index(i, j, k)] = 1;
    }
  });
  return beyond;
}

}  // namespace brainshift::segmentation
