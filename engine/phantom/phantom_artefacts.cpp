#include "phantom/phantom_artefacts.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "image/interpolation.h"

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
  Grid3 lattice_grid;
  lattice_grid.dims = n;
  std::vector<double> lattice(lattice_grid.voxel_count());
  for (auto& v : lattice) v = normal(rng);
  double sum2 = 0;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        // Within the hull of the lattice's nodes by the choice of n.
        double v = 0;
        trilinear_sample<TrilinearEdge::kCentreHull>(lattice_grid, lattice.data(),
                                                     Eigen::Vector3d(i * step[0], j * step[1], k * step[2]), &v);
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

std::vector<float> coil_array_bias(const Grid3& g, const Eigen::Vector3d& centre_mm, int loops,
                                   double array_radius_mm, double loop_radius_mm, double reference_radius_mm,
                                   double shading, std::mt19937_64& rng) {
  std::vector<float> out(g.voxel_count(), 1.f);
  if (loops <= 0 || shading <= 0) return out;
  // Fibonacci points on the sphere above z = -0.3 (the neck is open), the
  // whole arrangement turned about S-I by a random angle.
  std::uniform_real_distribution<double> turn(0, 2 * M_PI);
  const double phi0 = turn(rng), golden = M_PI * (3 - std::sqrt(5.0));
  std::vector<Eigen::Vector3d> coils;
  for (int n = 0; n < loops; ++n) {
    const double z = 1 - 1.3 * (n + 0.5) / loops, rho = std::sqrt(std::max(0.0, 1 - z * z)), phi = phi0 + golden * n;
    coils.push_back(centre_mm + array_radius_mm * Eigen::Vector3d(rho * std::cos(phi), rho * std::sin(phi), z));
  }
  const double a2 = loop_radius_mm * loop_radius_mm, a3 = a2 * loop_radius_mm;
  std::vector<double> rss(out.size());
  std::vector<double> reference;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d p = g.world_mm(i, j, k);
        double sum = 0;
        for (const auto& c : coils) {
          const double s = a3 / std::pow(a2 + (p - c).squaredNorm(), 1.5);
          sum += s * s;
        }
        const std::size_t v = g.index(i, j, k);
        rss[v] = std::sqrt(sum);
        if ((p - centre_mm).norm() <= reference_radius_mm) reference.push_back(rss[v]);
      }
  if (reference.empty()) return out;
  std::nth_element(reference.begin(), reference.begin() + reference.size() / 2, reference.end());
  const double median = reference[reference.size() / 2];
  for (std::size_t v = 0; v < out.size(); ++v) out[v] = static_cast<float>(std::pow(rss[v] / median, shading));
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
