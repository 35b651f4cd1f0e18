#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <ctime>
#include <limits>
#include <random>

#include "core/timer.h"
#include "image/distance_map.h"

namespace brainshift {
namespace {

Grid3 aniso_grid(std::array<int, 3> dims, Eigen::Vector3d spacing) {
  Grid3 g;
  g.dims = dims;
  g.world_from_voxel.diagonal().head<3>() = spacing;
  return g;
}

Mask random_mask(const Grid3& g, double fill, unsigned seed) {
  std::mt19937 rng(seed);
  std::bernoulli_distribution on(fill);
  Mask m(g, 0);
  for (auto& v : m.voxels) v = on(rng);
  return m;
}

double brute_force_distance(const Mask& m, int i, int j, int k) {
  const Eigen::Vector3d sp = m.grid.spacing_mm();
  double best = std::numeric_limits<double>::infinity();
  for (int c = 0; c < m.grid.dims[2]; ++c)
    for (int b = 0; b < m.grid.dims[1]; ++b)
      for (int a = 0; a < m.grid.dims[0]; ++a)
        if (m.at(a, b, c))
          best = std::min(best, Eigen::Vector3d((a - i) * sp[0], (b - j) * sp[1], (c - k) * sp[2]).norm());
  return best;
}

TEST(DistanceMap, MatchesBruteForceOnRandomAnisotropicMasks) {
  const Grid3 g = aniso_grid({13, 11, 9}, {0.7, 1.3, 2.9});
  for (double fill : {0.01, 0.05, 0.3}) {
    const Mask m = random_mask(g, fill, 42);
    const ImageF d = distance_to_mask_mm(m);
    for (int k = 0; k < 9; ++k)
      for (int j = 0; j < 11; ++j)
        for (int i = 0; i < 13; ++i)
          ASSERT_NEAR(d.at(i, j, k), brute_force_distance(m, i, j, k), 1e-4) << i << "," << j << "," << k;
  }
}

// The capped map is the full map up to the cap, and +infinity beyond it.
TEST(DistanceMap, CappedSquaredDistanceIsExactUpToTheCapAndInfiniteBeyond) {
  const Grid3 g = aniso_grid({23, 19, 11}, {0.9, 1.1, 2.5});
  for (double fill : {0.003, 0.02, 0.3})
    for (double cap_mm2 : {1.0, 6.76, 16.0}) {
      const Mask m = random_mask(g, fill, 7);
      const ImageF full = squared_distance_to_mask_mm2(m), capped = squared_distance_to_mask_mm2(m, cap_mm2);
      std::size_t beyond = 0;
      for (std::size_t v = 0; v < full.voxels.size(); ++v) {
        if (full.voxels[v] <= cap_mm2) {
          ASSERT_EQ(capped.voxels[v], full.voxels[v]) << v;
        } else {
          ASSERT_TRUE(std::isinf(capped.voxels[v])) << v;
          ++beyond;
        }
      }
      if (fill < 0.01) {
        EXPECT_GT(beyond, 0u);
      }
      const ImageF mm = distance_to_mask_mm(m), capped_mm = distance_to_mask_mm(m, std::sqrt(cap_mm2));
      for (std::size_t v = 0; v < mm.voxels.size(); ++v)
        if (full.voxels[v] <= cap_mm2) {
          ASSERT_EQ(capped_mm.voxels[v], mm.voxels[v]) << v;
        }
    }
}

TEST(DistanceMap, EmptyMaskIsInfinite) {
  const Mask m(aniso_grid({4, 4, 4}, {1, 1, 1}), 0);
  for (float v : distance_to_mask_mm(m).voxels) EXPECT_TRUE(std::isinf(v));
  for (float v : signed_distance_mm(m).voxels) EXPECT_GT(v, 0.f);
}

TEST(DistanceMap, SignedDistanceOfSlabHasZeroHalfwayBetweenBoundaryVoxels) {
  // Foreground for x index <= 4 on a 1 mm grid: surface at x = 4.5.
  const Grid3 g = aniso_grid({12, 3, 3}, {1, 1, 1});
  Mask m(g, 0);
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j)
      for (int i = 0; i <= 4; ++i) m.at(i, j, k) = 1;
  const ImageF s = signed_distance_mm(m);
  for (int i = 0; i < 12; ++i) EXPECT_NEAR(s.at(i, 1, 1), i - 4.5, 1e-6) << i;
}

TEST(DistanceMap, SignedDistanceOfBallApproximatesRadius) {
  const Grid3 g = aniso_grid({41, 41, 41}, {1, 1, 1});
  Mask m(g, 0);
  const double r = 12.0;
  for (int k = 0; k < 41; ++k)
    for (int j = 0; j < 41; ++j)
      for (int i = 0; i < 41; ++i) m.at(i, j, k) = Eigen::Vector3d(i - 20, j - 20, k - 20).norm() <= r;
  const ImageF s = signed_distance_mm(m);
  // Along an axis the voxelised surface is at r + 0.5 exactly; from the centre
  // the nearest background voxel may be off-axis (12,1,0), so only bound it.
  EXPECT_LT(s.at(20, 20, 20), -(r - 0.5));
  EXPECT_GE(s.at(20, 20, 20), -(r + 0.5) - 1e-5);
  EXPECT_NEAR(s.at(40, 20, 20), 20 - (r + 0.5), 1e-5);
}

TEST(DistanceMap, SignedDistanceOfIntraopSizedGridIsFast) {
  const Grid3 g = aniso_grid({256, 256, 60}, {0.94, 0.94, 2.5});
  Mask m(g, 0);
  for (int k = 10; k < 50; ++k)
    for (int j = 40; j < 210; ++j)
      for (int i = 50; i < 200; ++i)
        m.at(i, j, k) = Eigen::Vector3d((i - 125) * 0.94, (j - 125) * 0.94, (k - 30) * 2.5).norm() < 70;
  signed_distance_mm(m);  // warm caches and pages
  Stopwatch sw;
  const std::clock_t cpu0 = std::clock();
  const ImageF s = signed_distance_mm(m);
  const double cpu_seconds = double(std::clock() - cpu0) / CLOCKS_PER_SEC;  // summed over threads
  const double wall_seconds = sw.seconds();
  std::printf("signed_distance_mm 256x256x60: %.3f s wall, %.3f s CPU\n", wall_seconds, cpu_seconds);
  // Speed is a benchmark matter (docs/PERFORMANCE.md), printed here, never
  // asserted: a timed assertion on a shared machine measures the other jobs.
  EXPECT_LT(s.at(125, 125, 30), -45.f);  // the ball is cut at +-50 mm in z
}

}  // namespace
}  // namespace brainshift
