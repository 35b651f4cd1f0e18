#include "segmentation/potts.h"

#include <algorithm>
#include <cmath>

#include "core/parallel.h"

namespace brainshift::segmentation {
namespace {

void normalise(std::array<std::vector<float>, kTissues>& q, std::size_t v) {
  float sum = 0;
  for (int t = 0; t < kTissues; ++t) sum += q[t][v];
  if (sum > 0)
    for (int t = 0; t < kTissues; ++t) q[t][v] /= sum;
  else
    for (int t = 0; t < kTissues; ++t) q[t][v] = 1.f / kTissues;
}

}  // namespace

std::array<std::vector<float>, kTissues> potts_mean_field(const std::array<std::vector<float>, kTissues>& evidence,
                                                          const Grid3& grid, double beta, int sweeps) {
  const std::size_t V = grid.voxel_count();
  std::array<std::vector<float>, kTissues> q = evidence;
  // Jacobi sweeps: each voxel's update reads only the previous sweep, so the
  // slabs of slices run side by side with the same result on any core count.
  parallel_halves(V, 1 << 16, [&](std::size_t b, std::size_t e) {
    for (std::size_t v = b; v < e; ++v) normalise(q, v);
  });
  if (beta <= 0 || sweeps <= 0) return q;
  const Eigen::Vector3d spacing = grid.spacing_mm();
  const double h = spacing.minCoeff();
  const float w[3] = {static_cast<float>(beta * h / spacing[0]), static_cast<float>(beta * h / spacing[1]),
                      static_cast<float>(beta * h / spacing[2])};
  const auto& n = grid.dims;
  const std::ptrdiff_t stride[3] = {1, n[0], static_cast<std::ptrdiff_t>(n[0]) * n[1]};
  std::array<std::vector<float>, kTissues> next = q;
  const auto sweep_slices = [&](int k_begin, int k_end) {
    for (int k = k_begin; k < k_end; ++k)
      for (int j = 0; j < n[1]; ++j)
        for (int i = 0; i < n[0]; ++i) {
          const std::size_t v = grid.index(i, j, k);
          const int p[3] = {i, j, k};
          float field[kTissues] = {0, 0, 0};
          for (int a = 0; a < 3; ++a) {
            for (int side = -1; side <= 1; side += 2) {
              const int m = p[a] + side;
              if (m < 0 || m >= n[a]) continue;
              const std::size_t u = static_cast<std::size_t>(static_cast<std::ptrdiff_t>(v) + side * stride[a]);
              for (int t = 0; t < kTissues; ++t) field[t] += w[a] * q[t][u];
            }
          }
          const float top = std::max({field[0], field[1], field[2]});
          for (int t = 0; t < kTissues; ++t) next[t][v] = evidence[t][v] * std::exp(field[t] - top);
          normalise(next, v);
        }
  };
  for (int sweep = 0; sweep < sweeps; ++sweep) {
    parallel_halves(static_cast<std::size_t>(n[2]), 2, [&](std::size_t b, std::size_t e) {
      sweep_slices(static_cast<int>(b), static_cast<int>(e));
    });
    std::swap(q, next);
  }
  return q;
}

}  // namespace brainshift::segmentation
