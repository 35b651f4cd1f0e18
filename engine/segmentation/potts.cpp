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

// One row's neighbour field: w_x (left + right) + w_y (y_lo + y_hi) + w_z
// (z_lo + z_hi), summed in that order; a neighbour beyond the row's ends
// adds 0.
void sum_row(const float* __restrict c, const float* __restrict y_lo, const float* __restrict y_hi,
             const float* __restrict z_lo, const float* __restrict z_hi, const float w[3], int nx,
             float* __restrict out) {
  const auto at = [&](int i, float left, float right) {
    float f = 0;
    f += w[0] * left;
    f += w[0] * right;
    f += w[1] * y_lo[i];
    f += w[1] * y_hi[i];
    f += w[2] * z_lo[i];
    f += w[2] * z_hi[i];
    return f;
  };
  if (nx == 1) {
    out[0] = at(0, 0.f, 0.f);
    return;
  }
  out[0] = at(0, 0.f, c[1]);
  const float wx = w[0], wy = w[1], wz = w[2];
  for (int i = 1; i < nx - 1; ++i) {
    float f = 0;
    f += wx * c[i - 1];
    f += wx * c[i + 1];
    f += wy * y_lo[i];
    f += wy * y_hi[i];
    f += wz * z_lo[i];
    f += wz * z_hi[i];
    out[i] = f;
  }
  out[nx - 1] = at(nx - 1, c[nx - 2], 0.f);
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
  // A row of zeros stands for the rows off the grid.
  const std::vector<float> zeros(static_cast<std::size_t>(n[0]), 0.f);
  // The neighbours in a fixed order (-x, +x, -y, +y, -z, +z), a missing one
  // (off the grid) adding 0 (its weight times a zero): the same sums as
  // visiting only those present. Rows without branches inside vectorise.
  const auto sweep_slices = [&](int k_begin, int k_end) {
    for (int k = k_begin; k < k_end; ++k)
      for (int j = 0; j < n[1]; ++j) {
        const std::ptrdiff_t row = static_cast<std::ptrdiff_t>(grid.index(0, j, k));
        for (int t = 0; t < kTissues; ++t) {
          const float* qt = q[t].data() + row;
          const float* y_lo = j > 0 ? qt - stride[1] : zeros.data();
          const float* y_hi = j < n[1] - 1 ? qt + stride[1] : zeros.data();
          const float* z_lo = k > 0 ? qt - stride[2] : zeros.data();
          const float* z_hi = k < n[2] - 1 ? qt + stride[2] : zeros.data();
          float* out = next[t].data() + row;  // the field for now; evidence * exp(field - top) below
          sum_row(qt, y_lo, y_hi, z_lo, z_hi, w, n[0], out);
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
