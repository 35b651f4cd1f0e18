#include "phantom/phantom_artefacts.h"

#include <algorithm>
#include <array>
#include <cmath>

namespace brainshift {

// Smooth random field with unit-ish variance: Gaussian white noise on a coarse
// lattice (spacing correlation_mm) interpolated trilinearly, then scaled to
// rms_mm over the grid.
std::vector<float> smooth_noise(const Grid3& g, double correlation_mm, double rms_mm, std::mt19937_64& rng) {
  std::vector<float> out(g.voxel_count(), 0.f);
  if (rms_mm <= 0) return out;
  const Eigen::Vector3d sp = g.spacing_mm();
  std::array<int, 3> n;
  Eigen::Vector3d step;  // lattice cells per voxel
  for (int a = 0; a < 3; ++a) {
    step[a] = sp[a] / correlation_mm;
    n[a] = static_cast<int>(std::ceil((g.dims[a] - 1) * step[a])) + 2;
  }
  std::normal_distribution<double> normal(0, 1);
  std::vector<double> lattice(static_cast<std::size_t>(n[0]) * n[1] * n[2]);
  for (auto& v : lattice) v = normal(rng);
  auto L = [&](int i, int j, int k) { return lattice[i + static_cast<std::size_t>(n[0]) * (j + static_cast<std::size_t>(n[1]) * k)]; };
  double sum2 = 0;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const double x = i * step[0], y = j * step[1], z = k * step[2];
        const int x0 = static_cast<int>(x), y0 = static_cast<int>(y), z0 = static_cast<int>(z);
        const double fx = x - x0, fy = y - y0, fz = z - z0;
        double v = 0;
        for (int c = 0; c < 8; ++c) {
          const int dx = c & 1, dy = (c >> 1) & 1, dz = (c >> 2) & 1;
          v += (dx ? fx : 1 - fx) * (dy ? fy : 1 - fy) * (dz ? fz : 1 - fz) * L(x0 + dx, y0 + dy, z0 + dz);
        }
        out[g.index(i, j, k)] = static_cast<float>(v);
        sum2 += v * v;
      }
  const double scale = rms_mm / std::sqrt(sum2 / static_cast<double>(out.size()));
  for (auto& v : out) v = static_cast<float>(v * scale);
  return out;
}

// exp(amplitude * g) with g a random quadratic polynomial over the grid box
// normalised to max |g| = 1: a smooth multiplicative bias like a receive coil's.
std::vector<float> bias_field(const Grid3& g, double amplitude, std::mt19937_64& rng) {
  std::vector<float> out(g.voxel_count(), 1.f);
  if (amplitude <= 0) return out;
  std::uniform_real_distribution<double> coef(-1, 1);
  std::array<double, 9> c;
  for (auto& v : c) v = coef(rng);
  auto poly = [&](double x, double y, double z) {
    return c[0] * x + c[1] * y + c[2] * z + c[3] * x * y + c[4] * x * z + c[5] * y * z + c[6] * x * x + c[7] * y * y +
           c[8] * z * z;
  };
  double max_abs = 1e-12;
  std::vector<double> values(out.size());
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const double v = poly(2.0 * i / (g.dims[0] - 1) - 1, 2.0 * j / (g.dims[1] - 1) - 1, 2.0 * k / (g.dims[2] - 1) - 1);
        values[g.index(i, j, k)] = v;
        max_abs = std::max(max_abs, std::abs(v));
      }
  for (std::size_t v = 0; v < out.size(); ++v) out[v] = static_cast<float>(std::exp(amplitude * values[v] / max_abs));
  return out;
}

void add_rician_noise(std::vector<float>& voxels, double sigma, std::mt19937_64& rng) {
  std::normal_distribution<double> normal(0, sigma);
  for (auto& v : voxels) {
    const double re = v + normal(rng), im = normal(rng);
    v = static_cast<float>(std::sqrt(re * re + im * im));
  }
}

}  // namespace brainshift
