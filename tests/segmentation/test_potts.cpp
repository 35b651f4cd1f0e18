// The Potts mean-field smoothing (segmentation/potts.h): the equations as
// written, computed on both cores or on one, and what smoothing does.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>

#include "core/parallel.h"
#include "segmentation/potts.h"

using namespace brainshift;
using namespace brainshift::segmentation;

namespace {

Grid3 grid(int nx, int ny, int nz, double sx, double sy, double sz) {
  Grid3 g;
  g.dims = {nx, ny, nz};
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  g.world_from_voxel(0, 0) = sx;
  g.world_from_voxel(1, 1) = sy;
  g.world_from_voxel(2, 2) = sz;
  return g;
}

// q_t(x) ~ e_t(x) exp(sum over the face neighbours present of w_axis q_t(n)),
// Jacobi sweeps, straight from the definition (potts.h).
std::array<std::vector<float>, kTissues> by_definition(const std::array<std::vector<float>, kTissues>& e,
                                                       const Grid3& g, double beta, int sweeps) {
  const std::size_t V = g.voxel_count();
  auto normalise = [](std::array<std::vector<float>, kTissues>& q, std::size_t v) {
    float sum = 0;
    for (int t = 0; t < kTissues; ++t) sum += q[t][v];
    for (int t = 0; t < kTissues; ++t) q[t][v] = sum > 0 ? q[t][v] / sum : 1.f / kTissues;
  };
  auto q = e;
  for (std::size_t v = 0; v < V; ++v) normalise(q, v);
  const Eigen::Vector3d s = g.spacing_mm();
  const float w[3] = {static_cast<float>(beta * s.minCoeff() / s[0]), static_cast<float>(beta * s.minCoeff() / s[1]),
                      static_cast<float>(beta * s.minCoeff() / s[2])};
  auto next = q;
  for (int sweep = 0; sweep < sweeps; ++sweep) {
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          const std::size_t v = g.index(i, j, k);
          float field[kTissues] = {0, 0, 0};
          for (int a = 0; a < 3; ++a)
            for (int side = -1; side <= 1; side += 2) {
              int n[3] = {i, j, k};
              n[a] += side;
              if (n[a] < 0 || n[a] >= g.dims[a]) continue;
              for (int t = 0; t < kTissues; ++t) field[t] += w[a] * q[t][g.index(n[0], n[1], n[2])];
            }
          const float top = std::max({field[0], field[1], field[2]});
          for (int t = 0; t < kTissues; ++t) next[t][v] = e[t][v] * std::exp(field[t] - top);
          normalise(next, v);
        }
    std::swap(q, next);
  }
  return q;
}

std::array<std::vector<float>, kTissues> random_evidence(const Grid3& g, std::uint32_t seed) {
  std::array<std::vector<float>, kTissues> e;
  for (auto& t : e) t.resize(g.voxel_count());
  for (std::size_t v = 0; v < g.voxel_count(); ++v)
    for (int t = 0; t < kTissues; ++t) {
      seed = seed * 1664525u + 1013904223u;
      // Some voxels decided, some even, some with an exact tie.
      e[t][v] = (seed >> 30) == 0 ? 0.f : static_cast<float>((seed >> 8) % 1000) / 1000.f;
    }
  return e;
}

}  // namespace

TEST(Potts, EqualsTheDefinitionOnOneCoreAndOnTwo) {
  // Large enough that both the per-voxel and the per-slice loops split.
  const Grid3 g = grid(70, 50, 41, 0.9375, 0.9375, 2.5);
  const auto e = random_evidence(g, 7);
  const auto expected = by_definition(e, g, 0.35, 3);
  const auto two = potts_mean_field(e, g, 0.35, 3);
  std::array<std::vector<float>, kTissues> one;
  {
    SerialOnThisThread serial;
    one = potts_mean_field(e, g, 0.35, 3);
  }
  for (int t = 0; t < kTissues; ++t) {
    EXPECT_EQ(two[t], expected[t]) << "tissue " << t;
    EXPECT_EQ(one[t], expected[t]) << "tissue " << t;
  }
}

TEST(Potts, AnIsolatedVoxelTakesItsNeighboursTissueAndAnEvenRegionStaysEven) {
  const Grid3 g = grid(9, 9, 9, 1, 1, 1);
  std::array<std::vector<float>, kTissues> e;
  for (auto& t : e) t.assign(g.voxel_count(), 0.f);
  for (std::size_t v = 0; v < g.voxel_count(); ++v) {
    e[0][v] = 0.6f;  // tissue 0 mildly likelier everywhere ...
    e[1][v] = 0.4f;
  }
  const std::size_t centre = g.index(4, 4, 4);
  e[0][centre] = 0.45f;  // ... but at one voxel, by less than the neighbours' pull
  e[1][centre] = 0.55f;
  const auto q = potts_mean_field(e, g, 0.35, 3);
  EXPECT_GT(q[0][centre], q[1][centre]);
  EXPECT_EQ(q[2][centre], 0.f);  // no evidence, no probability
  // Without coupling the posterior is the normalised evidence.
  const auto plain = potts_mean_field(e, g, 0.0, 3);
  EXPECT_FLOAT_EQ(plain[1][centre], 0.55f);
  EXPECT_FLOAT_EQ(plain[0][g.index(0, 0, 0)], 0.6f);
}

TEST(Parallel, SerialOnThisThreadKeepsTheLoopOnTheCallingThread) {
  int calls = 0;
  {
    SerialOnThisThread serial;
    {
      SerialOnThisThread nested;
    }
    EXPECT_TRUE(SerialOnThisThread::active());  // the nested guard restored, not cleared
    parallel_halves(1u << 20, 1, [&](std::size_t b, std::size_t e) {
      ++calls;  // one call on this thread: no race on the counter
      EXPECT_EQ(b, 0u);
      EXPECT_EQ(e, 1u << 20);
    });
  }
  EXPECT_EQ(calls, 1);
  EXPECT_FALSE(SerialOnThisThread::active());
}
