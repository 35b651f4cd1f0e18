#include "image/gaussian_smooth.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/parallel.h"

namespace brainshift {

void gaussian_smooth_voxels(ImageF& image, const Eigen::Vector3d& sigma_voxels) {
  const Grid3& g = image.grid;
  for (int axis = 0; axis < 3; ++axis) {
    const double sigma = sigma_voxels[axis];
    if (sigma < 0.05 || g.dims[axis] < 2) continue;
    const int half = static_cast<int>(std::ceil(3 * sigma));
    std::vector<double> w(2 * half + 1);
    double sum = 0;
    for (int t = -half; t <= half; ++t) sum += w[t + half] = std::exp(-0.5 * t * t / (sigma * sigma));
    for (auto& x : w) x /= sum;
    const std::vector<float> src = image.voxels;
    const std::size_t stride = axis == 0 ? 1 : axis == 1 ? static_cast<std::size_t>(g.dims[0])
                                                         : static_cast<std::size_t>(g.dims[0]) * g.dims[1];
    const int n = g.dims[axis];
    // Each output voxel reads only src: the slices split over two cores
    // give the same result as one.
    parallel_halves(static_cast<std::size_t>(g.dims[2]), 8, [&](std::size_t k_begin, std::size_t k_end) {
      for (int k = static_cast<int>(k_begin); k < static_cast<int>(k_end); ++k)
        for (int j = 0; j < g.dims[1]; ++j)
          for (int i = 0; i < g.dims[0]; ++i) {
            const int at = axis == 0 ? i : axis == 1 ? j : k;
            const std::size_t v = g.index(i, j, k);
            const std::size_t line = v - static_cast<std::size_t>(at) * stride;
            double acc = 0;
            for (int t = -half; t <= half; ++t)
              acc += w[t + half] * src[line + static_cast<std::size_t>(std::clamp(at + t, 0, n - 1)) * stride];
            image.voxels[v] = static_cast<float>(acc);
          }
    });
  }
}

}  // namespace brainshift
