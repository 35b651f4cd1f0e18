#include "field/field_fill.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "core/parallel.h"
#include "image/interpolation.h"

namespace brainshift {
namespace {

struct Level {
  std::array<int, 3> dims{1, 1, 1};
  std::array<int, 3> factor{1, 1, 1};  // how this level was reduced from the finer one
  std::array<double, 3> spacing{1, 1, 1};
  std::vector<Eigen::Vector3f> values;  // normalised (weighted mean)
  std::vector<float> weight;            // in [0, 1]

  std::size_t index(int i, int j, int k) const {
    return static_cast<std::size_t>(i) +
           static_cast<std::size_t>(dims[0]) * (static_cast<std::size_t>(j) +
                                                static_cast<std::size_t>(dims[1]) * k);
  }
  std::size_t size() const {
    return static_cast<std::size_t>(dims[0]) * dims[1] * dims[2];
  }
};

bool is_top(const Level& level) {
  return level.dims[0] == 1 && level.dims[1] == 1 && level.dims[2] == 1;
}

Level reduce(const Level& fine) {
  Level coarse;
  const double finest = std::min({fine.spacing[0], fine.spacing[1], fine.spacing[2]});
  for (int a = 0; a < 3; ++a) {
    const bool halve = fine.dims[a] > 1 && fine.spacing[a] <= 1.5 * finest;
    coarse.factor[a] = halve ? 2 : 1;
    coarse.dims[a] = (fine.dims[a] + coarse.factor[a] - 1) / coarse.factor[a];
    coarse.spacing[a] = fine.spacing[a] * coarse.factor[a];
  }
  std::vector<Eigen::Vector3f> sum(coarse.size(), Eigen::Vector3f::Zero());
  std::vector<float> wsum(coarse.size(), 0.f);
  for (int k = 0; k < fine.dims[2]; ++k) {
    for (int j = 0; j < fine.dims[1]; ++j) {
      const std::size_t crow = coarse.index(0, j / coarse.factor[1], k / coarse.factor[2]);
      std::size_t f = fine.index(0, j, k);
      for (int i = 0; i < fine.dims[0]; ++i, ++f) {
        const float w = fine.weight[f];
        if (w <= 0.f) continue;
        const std::size_t c = crow + static_cast<std::size_t>(i / coarse.factor[0]);
        sum[c] += w * fine.values[f];
        wsum[c] += w;
      }
    }
  }
  coarse.values.resize(coarse.size());
  coarse.weight.resize(coarse.size());
  for (std::size_t c = 0; c < coarse.size(); ++c) {
    coarse.values[c] = wsum[c] > 0.f ? Eigen::Vector3f(sum[c] / wsum[c]) : Eigen::Vector3f::Zero();
    coarse.weight[c] = std::min(1.f, wsum[c]);
  }
  return coarse;
}

// Cell-centred correspondence: fine voxel i sits at coarse coordinate (i + 0.5)/f - 0.5.
struct AxisWeights {
  std::vector<int> lo, hi;
  std::vector<float> t;
};

AxisWeights axis_weights(int fine_n, int coarse_n, int factor) {
  AxisWeights w;
  w.lo.resize(fine_n);
  w.hi.resize(fine_n);
  w.t.resize(fine_n);
  for (int i = 0; i < fine_n; ++i) {
    double c = (i + 0.5) / factor - 0.5;
    c = std::clamp(c, 0.0, static_cast<double>(coarse_n - 1));
    const int lo = std::min(static_cast<int>(std::floor(c)), coarse_n - 1);
    w.lo[i] = lo;
    w.hi[i] = std::min(lo + 1, coarse_n - 1);
    w.t[i] = static_cast<float>(c - lo);
  }
  return w;
}

struct Upsampler {
  const Level& coarse;
  AxisWeights ax, ay, az;

  Upsampler(const Level& c, const Level& fine)
      : coarse(c),
        ax(axis_weights(fine.dims[0], c.dims[0], c.factor[0])),
        ay(axis_weights(fine.dims[1], c.dims[1], c.factor[1])),
        az(axis_weights(fine.dims[2], c.dims[2], c.factor[2])) {}

  // The cell comes from the per-axis tables; image/interpolation.h blends it.
  Eigen::Vector3f at(int i, int j, int k) const {
    const std::size_t sy = static_cast<std::size_t>(coarse.dims[0]), sz = sy * static_cast<std::size_t>(coarse.dims[1]);
    TrilinearCell<float> cell;
    cell.origin = coarse.index(ax.lo[i], ay.lo[j], az.lo[k]);
    cell.step = {static_cast<std::size_t>(ax.hi[i] - ax.lo[i]), static_cast<std::size_t>(ay.hi[j] - ay.lo[j]) * sy,
                 static_cast<std::size_t>(az.hi[k] - az.lo[k]) * sz};
    cell.t = {ax.t[i], ay.t[j], az.t[k]};
    return trilinear_blend(trilinear_corners<float>(coarse.values.data(), cell), cell);
  }
};

// fine = w * fine + (1 - w) * trilinear(coarse); afterwards fine is complete.
void pull(const Level& coarse, Level& fine) {
  const Upsampler up(coarse, fine);
  for (int k = 0; k < fine.dims[2]; ++k) {
    for (int j = 0; j < fine.dims[1]; ++j) {
      std::size_t f = fine.index(0, j, k);
      for (int i = 0; i < fine.dims[0]; ++i, ++f) {
        const float w = fine.weight[f];
        if (w >= 1.f) continue;
        fine.values[f] = w * fine.values[f] + (1.f - w) * up.at(i, j, k);
        fine.weight[f] = 1.f;
      }
    }
  }
}

// Finest level: weights are 0/1 and only the listed voxels are needed.
void pull_targets(const Level& coarse, Level& fine, const std::vector<std::uint32_t>& targets) {
  const Upsampler up(coarse, fine);
  const std::size_t nx = fine.dims[0], nxy = nx * fine.dims[1];
  for (const std::uint32_t f : targets) {
    if (fine.weight[f] >= 1.f) continue;
    fine.values[f] = up.at(static_cast<int>(f % nx), static_cast<int>((f % nxy) / nx),
                           static_cast<int>(f / nxy));
  }
}

}  // namespace

void fill_push_pull(const Grid3& grid, const std::vector<std::uint8_t>& known,
                    const std::vector<std::uint32_t>& targets, std::vector<Eigen::Vector3f>& values) {
  Level base;
  base.dims = grid.dims;
  const Eigen::Vector3d sp = grid.spacing_mm();
  base.spacing = {sp.x(), sp.y(), sp.z()};
  base.values = std::move(values);
  base.weight.resize(base.size());
  bool any_known = false;
  for (std::size_t v = 0; v < base.size(); ++v) {
    base.weight[v] = known[v] ? 1.f : 0.f;
    any_known = any_known || known[v];
  }
  if (!any_known) {
    for (const std::uint32_t v : targets) base.values[v] = Eigen::Vector3f::Zero();
    values = std::move(base.values);
    return;
  }
  std::vector<Level> pyramid;
  pyramid.push_back(std::move(base));
  while (!is_top(pyramid.back())) pyramid.push_back(reduce(pyramid.back()));
  // The 1x1x1 top holds the mean of all known values and has weight 1.
  for (std::size_t l = pyramid.size() - 1; l > 1; --l) pull(pyramid[l], pyramid[l - 1]);
  if (pyramid.size() > 1) pull_targets(pyramid[1], pyramid[0], targets);
  values = std::move(pyramid.front().values);
}

void relax_laplace(const Grid3& grid, const std::vector<std::uint32_t>& free_voxels,
                   int sweeps, std::vector<Eigen::Vector3f>& values) {
  const Eigen::Vector3d sp = grid.spacing_mm();
  const std::array<float, 3> w{static_cast<float>(1.0 / (sp.x() * sp.x())),
                               static_cast<float>(1.0 / (sp.y() * sp.y())),
                               static_cast<float>(1.0 / (sp.z() * sp.z()))};
  const std::size_t nx = grid.dims[0], nxy = nx * grid.dims[1];
  const std::array<std::size_t, 3> stride{1, nx, nxy};
  // Red-black ordering: a voxel's 6 neighbours all have the other colour, so
  // each half-sweep updates its voxels independently (in two threads, with
  // the same result as one). Bit 2a of `bits`: neighbour at -1 along axis a
  // exists; bit 2a+1: at +1. Decoded once, so the sweeps do no divisions.
  struct Free {
    std::uint32_t v;
    std::uint8_t bits;
  };
  std::array<std::vector<Free>, 2> colour;
  for (const std::uint32_t v : free_voxels) {
    const std::array<int, 3> ijk{static_cast<int>(v % nx), static_cast<int>((v % nxy) / nx),
                                 static_cast<int>(v / nxy)};
    std::uint8_t bits = 0;
    for (int a = 0; a < 3; ++a) {
      if (ijk[a] > 0) bits |= std::uint8_t(1u << (2 * a));
      if (ijk[a] + 1 < grid.dims[a]) bits |= std::uint8_t(1u << (2 * a + 1));
    }
    colour[(ijk[0] + ijk[1] + ijk[2]) & 1].push_back({v, bits});
  }
  auto relax = [&](const std::vector<Free>& list, std::size_t begin, std::size_t end) {
    for (std::size_t n = begin; n < end; ++n) {
      const std::size_t v = list[n].v;
      const std::uint8_t bits = list[n].bits;
      Eigen::Vector3f sum = Eigen::Vector3f::Zero();
      float wsum = 0.f;
      for (int a = 0; a < 3; ++a) {
        if (bits & (1u << (2 * a))) {
          sum += w[a] * values[v - stride[a]];
          wsum += w[a];
        }
        if (bits & (1u << (2 * a + 1))) {
          sum += w[a] * values[v + stride[a]];
          wsum += w[a];
        }
      }
      if (wsum > 0.f) values[v] = sum / wsum;
    }
  };
  for (int s = 0; s < sweeps; ++s)
    for (const auto& list : colour)
      parallel_halves(list.size(), 16384, [&](std::size_t b, std::size_t e) { relax(list, b, e); });
}

}  // namespace brainshift
