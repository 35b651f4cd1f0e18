// A folded pull-back field is repaired locally; the rest of it is untouched.
#include <gtest/gtest.h>

#include <cmath>

#include "field/metrics.h"
#include "field/unfold.h"

using namespace brainshift;

namespace {

// u_x = -A (x - c) g(r): det(I + grad u) = 1 - A g at the centre, so A = 1.6
// folds the middle (det -0.6) while far voxels keep det ~1.
VectorImage3 folded_field(double amplitude) {
  Grid3 g;
  g.dims = {32, 32, 24};
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  g.world_from_voxel(2, 2) = 1.5;
  VectorImage3 f(g);
  const Eigen::Vector3d c = g.world_mm(16, 16, 12);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d x = g.world_mm(i, j, k) - c;
        const double w = std::exp(-x.squaredNorm() / (2 * 4.0 * 4.0));
        f.vectors[g.index(i, j, k)] = Eigen::Vector3f(static_cast<float>(-amplitude * x.x() * w), 1.0f, 0.0f);
      }
  return f;
}

}  // namespace

TEST(Unfold, RepairsAFoldLocallyAndReportsIt) {
  VectorImage3 f = folded_field(1.6);
  Mask everywhere(f.grid, 1);
  ASSERT_LT(jacobian_stats(f, &everywhere).min_det, 0.0);
  const VectorImage3 before = f;
  UnfoldStats s;
  EXPECT_TRUE(unfold_field(f, everywhere, UnfoldParameters{}, &s));
  EXPECT_GE(jacobian_stats(f, &everywhere).min_det, 0.1 - 1e-6);
  EXPECT_GT(s.bad_voxels_before, 0u);
  EXPECT_EQ(s.bad_voxels_after, 0u);
  EXPECT_GT(s.changed_voxels, 0u);
  EXPECT_LT(s.changed_voxels, f.vectors.size() / 4) << "the repair must stay local";
  // Far from the fold the field is exactly as it was.
  EXPECT_EQ(f.vectors[f.grid.index(1, 1, 1)], before.vectors[before.grid.index(1, 1, 1)]);
  EXPECT_EQ(f.vectors[f.grid.index(30, 2, 20)], before.vectors[before.grid.index(30, 2, 20)]);
}

TEST(Unfold, LeavesASoundFieldAlone) {
  VectorImage3 f = folded_field(0.3);  // det >= 0.7 everywhere
  const VectorImage3 before = f;
  Mask everywhere(f.grid, 1);
  UnfoldStats s;
  EXPECT_TRUE(unfold_field(f, everywhere, UnfoldParameters{}, &s));
  EXPECT_EQ(s.rounds, 0);
  EXPECT_EQ(s.changed_voxels, 0u);
  EXPECT_EQ(f.vectors, before.vectors);
}

TEST(Unfold, OnlyTheRegionCounts) {
  VectorImage3 f = folded_field(1.6);
  Mask nowhere(f.grid, 0);
  UnfoldStats s;
  EXPECT_TRUE(unfold_field(f, nowhere, UnfoldParameters{}, &s));
  EXPECT_EQ(s.bad_voxels_before, 0u);
  UnfoldParameters one_round;
  one_round.max_rounds = 1;
  VectorImage3 g = folded_field(3.0);
  Mask everywhere(g.grid, 1);
  EXPECT_FALSE(unfold_field(g, everywhere, one_round, &s)) << "a deep fold is not repaired in one round";
  EXPECT_GT(s.bad_voxels_after, 0u);
}
