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
  // The neighbours in a fixed order (-x, +x, -y, +y, -z, +z), a missing one
  // (off the grid) adding 0: the same sums as visiting only those present.
  const auto sweep_slices = [&](int k_begin, int k_end) {
    for (int k = k_begin; k < k_end; ++k)
      for (int j = 0; j < n[1]; ++j) {
        const bool has[4] = {j > 0, j < n[1] - 1, k > 0, k < n[2] - 1};
        const std::ptrdiff_t row = static_cast<std::ptrdiff_t>(grid.index(0, j, k));
        for (int t = 0; t < kTissues; ++t) {
          const float* qt = q[t].data();
          float* out = next[t].data();
          for (int i = 0; i < n[0]; ++i) {
            const std::ptrdiff_t v = row + i;
            float f = 0;
            f += i > 0 ? w[0] * qt[v - 1] : 0.f;
            f += i < n[0] - 1 ? w[0] * qt[v + 1] : 0.f;
            f += has[0] ? w[1] * qt[v - stride[1]] : 0.f;
            f += has[1] ? w[1] * qt[v + stride[1]] : 0.f;
            f += has[2] ? w[2] * qt[v - stride[2]] : 0.f;
            f += has[3] ? w[2] * qt[v + stride[2]] : 0.f;
            out[v] = f;  // the field for now; evidence * exp(field - top) below
          }
        }
        for (int i = 0; i < n[0]; ++i) {
          const std::size_t v = static_cast<std::size_t>(row + i);
          const float top = std::max({next[0][v], next[1][v], next[2][v]});
          // exp(0) is exactly 1: the likeliest tissue needs no exp.
          for (int t = 0; t < kTissues; ++t)
            next[t][v] = next[t][v] == top ? evidence[t][v] : evidence[t][v] * std::exp(next[t][v] - top);
          normalise(next, v);
        }
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
