#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

#include "core/errors.h"
#include "image/image_stats.h"
#include "image/morphology.h"

namespace brainshift {
namespace {

Grid3 grid(std::array<int, 3> dims, Eigen::Vector3d spacing = {1, 1, 1}) {
  Grid3 g;
  g.dims = dims;
  g.world_from_voxel.diagonal().head<3>() = spacing;
  return g;
}

// Lattice points with |(i,j,k) * spacing| <= r, counted directly.
std::size_t lattice_points_in_ball(Eigen::Vector3d spacing, double r) {
  std::size_t n = 0;
  const int m = 40;
  for (int k = -m; k <= m; ++k)
    for (int j = -m; j <= m; ++j)
      for (int i = -m; i <= m; ++i)
        n += Eigen::Vector3d(i * spacing[0], j * spacing[1], k * spacing[2]).norm() <= r + 1e-9;
  return n;
}

TEST(Morphology, DilatedPointIsExactAnisotropicBall) {
  const Eigen::Vector3d sp(0.8, 1.0, 2.0);
  Mask m(grid({41, 41, 21}, sp), 0);
  m.at(20, 20, 10) = 1;
  for (double r : {1.0, 2.0, 5.0, 7.3}) {
    const Mask d = dilate(m, r);
    EXPECT_EQ(count_nonzero(d), lattice_points_in_ball(sp, r)) << r;
    // Large balls approach the continuous volume.
    if (r > 7) {
      EXPECT_NEAR(volume_ml(d), 4.0 / 3.0 * M_PI * r * r * r / 1000.0, 0.05 * 4.0 / 3.0 * M_PI * r * r * r / 1000.0);
    }
  }
}

TEST(Morphology, ErodeUndoesDilateOfBallAndOpenRemovesThinStrand) {
  Mask ball(grid({31, 31, 31}), 0);
  for (int k = 0; k < 31; ++k)
    for (int j = 0; j < 31; ++j)
      for (int i = 0; i < 31; ++i) ball.at(i, j, k) = Eigen::Vector3d(i - 15, j - 15, k - 15).norm() <= 8;
  EXPECT_EQ(erode(dilate(ball, 3), 3).voxels, ball.voxels);
  // Erosion by r keeps voxels whose nearest background is farther than r.
  const Mask e = erode(ball, 3);
  EXPECT_TRUE(e.at(15, 15, 15));
  EXPECT_FALSE(e.at(15, 15, 15 + 6));
  EXPECT_TRUE(e.at(15, 15, 15 + 5));
  // A one-voxel strand sticking out of the ball disappears with open(1.5).
  Mask strand = ball;
  for (int i = 24; i < 30; ++i) strand.at(i, 15, 15) = 1;
  const Mask opened = open(strand, 1.5);
  EXPECT_FALSE(opened.at(27, 15, 15));
  EXPECT_TRUE(opened.at(15, 15, 15));
}

TEST(Morphology, CloseFillsNarrowGap) {
  Mask m(grid({20, 10, 10}), 0);
  for (int k = 2; k < 8; ++k)
    for (int j = 2; j < 8; ++j)
      for (int i = 2; i < 18; ++i) m.at(i, j, k) = (i != 10);  // a one-voxel slit
  const Mask c = close(m, 1.0);
  EXPECT_TRUE(c.at(10, 5, 5));
  int n = 0;
  connected_components(m, 6, &n);
  EXPECT_EQ(n, 2);
  connected_components(c, 6, &n);
  EXPECT_EQ(n, 1);
}

TEST(Morphology, ComponentCountsDependOnConnectivity) {
  Mask m(grid({10, 10, 10}), 0);
  m.at(1, 1, 1) = 1;
  m.at(2, 2, 2) = 1;  // touches the first only at a corner
  m.at(6, 6, 6) = 1;
  m.at(6, 7, 6) = 1;  // face neighbour
  m.at(6, 8, 6) = 1;
  int n6 = 0, n26 = 0;
  const auto c6 = connected_components(m, 6, &n6);
  connected_components(m, 26, &n26);
  EXPECT_EQ(n6, 3);
  EXPECT_EQ(n26, 2);
  EXPECT_EQ(c6.at(6, 6, 6), c6.at(6, 8, 6));
  EXPECT_NE(c6.at(1, 1, 1), c6.at(2, 2, 2));
  const Mask big = largest_component(m, 6);
  EXPECT_EQ(count_nonzero(big), 3u);
  EXPECT_TRUE(big.at(6, 7, 6));
  EXPECT_THROW(connected_components(m, 18, nullptr), InputError);
  EXPECT_EQ(count_nonzero(largest_component(Mask(m.grid, 0), 6)), 0u);
}

TEST(Morphology, FillHolesFillsEnclosedCavityOnly) {
  Mask m(grid({12, 12, 12}), 0);
  for (int k = 2; k <= 9; ++k)
    for (int j = 2; j <= 9; ++j)
      for (int i = 2; i <= 9; ++i) m.at(i, j, k) = !(i >= 4 && i <= 7 && j >= 4 && j <= 7 && k >= 4 && k <= 7);
  // A second cavity opened to the outside through a tunnel is not a hole.
  Mask open_cavity = m;
  for (int i = 0; i <= 4; ++i) open_cavity.at(i, 5, 5) = 0;
  const Mask filled = fill_holes(m);
  EXPECT_EQ(count_nonzero(filled), 8u * 8 * 8);
  const Mask not_filled = fill_holes(open_cavity);
  EXPECT_EQ(not_filled.voxels, open_cavity.voxels);
}

// The background 6-connected to the grid's faces, by the definition: a
// breadth-first search from every background voxel on a face, bounds
// checked at every step.
Mask holes_filled_by_definition(const Mask& m) {
  const auto& d = m.grid.dims;
  std::vector<char> outside(m.voxels.size(), 0);
  std::vector<std::array<int, 3>> queue;
  auto visit = [&](int i, int j, int k) {
    if (i < 0 || j < 0 || k < 0 || i >= d[0] || j >= d[1] || k >= d[2]) return;
    const std::size_t v = m.grid.index(i, j, k);
    if (m.voxels[v] || outside[v]) return;
    outside[v] = 1;
    queue.push_back({i, j, k});
  };
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (i == 0 || j == 0 || k == 0 || i == d[0] - 1 || j == d[1] - 1 || k == d[2] - 1) visit(i, j, k);
  for (std::size_t q = 0; q < queue.size(); ++q) {
    const auto [i, j, k] = queue[q];
    visit(i + 1, j, k), visit(i - 1, j, k), visit(i, j + 1, k);
    visit(i, j - 1, k), visit(i, j, k + 1), visit(i, j, k - 1);
  }
  Mask out(m.grid, 0);
  for (std::size_t v = 0; v < out.voxels.size(); ++v) out.voxels[v] = m.voxels[v] || !outside[v];
  return out;
}

// 6-connected components by the definition: a breadth-first search from each
// unnumbered mask voxel in raster order, numbered in that order.
Image3<std::int32_t> components_by_definition(const Mask& m, int* count) {
  const auto& d = m.grid.dims;
  Image3<std::int32_t> out(m.grid, 0);
  std::int32_t n = 0;
  std::vector<std::array<int, 3>> queue;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        if (!m.at(i, j, k) || out.at(i, j, k)) continue;
        out.at(i, j, k) = ++n;
        queue.assign(1, {i, j, k});
        for (std::size_t q = 0; q < queue.size(); ++q) {
          const auto [a, b, c] = queue[q];
          for (const auto& [da, db, dc] : {std::array<int, 3>{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}}) {
            const int x = a + da, y = b + db, z = c + dc;
            if (x < 0 || y < 0 || z < 0 || x >= d[0] || y >= d[1] || z >= d[2]) continue;
            if (!m.at(x, y, z) || out.at(x, y, z)) continue;
            out.at(x, y, z) = n;
            queue.push_back({x, y, z});
          }
        }
      }
  *count = n;
  return out;
}

TEST(Morphology, ComponentsAgreeWithTheDefinitionOnRandomMasks) {
  // Runs that touch at one voxel, U shapes joined only in a later row or
  // slice, and numbering in raster order of each component's first voxel.
  std::uint32_t state = 777;
  auto next = [&state] { return state = state * 1664525u + 1013904223u; };
  for (const std::array<int, 3> dims : {std::array<int, 3>{17, 13, 11}, {9, 21, 1}, {1, 1, 7}, {31, 4, 6}})
    for (const unsigned percent : {15u, 35u, 50u, 65u, 85u}) {
      Mask m(grid(dims), 0);
      for (auto& v : m.voxels) v = (next() >> 8) % 100 < percent;
      int n = 0, n_def = 0;
      const auto c = connected_components(m, 6, &n);
      const auto c_def = components_by_definition(m, &n_def);
      EXPECT_EQ(n, n_def) << dims[0] << "x" << dims[1] << "x" << dims[2] << " at " << percent << " %";
      EXPECT_EQ(c.voxels, c_def.voxels) << dims[0] << "x" << dims[1] << "x" << dims[2] << " at " << percent << " %";
    }
}

TEST(Morphology, FillHolesAgreesWithTheDefinitionOnRandomMasks) {
  // Random masks of several densities on odd grids (including a single
  // slice and a single row, where every voxel is on a face).
  std::uint32_t state = 12345;
  auto next = [&state] { return state = state * 1664525u + 1013904223u; };
  for (const std::array<int, 3> dims : {std::array<int, 3>{17, 13, 11}, {9, 21, 1}, {1, 1, 7}, {23, 5, 8}})
    for (const unsigned percent : {20u, 45u, 60u, 75u}) {
      Mask m(grid(dims), 0);
      for (auto& v : m.voxels) v = (next() >> 8) % 100 < percent;
      const Mask filled = fill_holes(m);
      EXPECT_EQ(filled.voxels, holes_filled_by_definition(m).voxels)
          << dims[0] << "x" << dims[1] << "x" << dims[2] << " at " << percent << " %";
    }
  // Masks inside a part of the grid (fill_holes floods only the mask's
  // bounding box): holes on the box's faces, background around it.
  for (const unsigned percent : {30u, 55u, 70u}) {
    Mask m(grid({19, 15, 12}), 0);
    for (int k = 3; k <= 9; ++k)
      for (int j = 2; j <= 11; ++j)
        for (int i = 5; i <= 13; ++i) m.at(i, j, k) = (next() >> 8) % 100 < percent;
    EXPECT_EQ(fill_holes(m).voxels, holes_filled_by_definition(m).voxels) << "sub-box at " << percent << " %";
  }
  EXPECT_EQ(count_nonzero(fill_holes(Mask(grid({4, 5, 6}), 0))), 0u);
}

// Dilation and erosion by the definition: a voxel is within r of the mask
// (of the background, for the erosion) when some such voxel of the grid lies
// within r of it; off the grid is neither.
Mask by_definition(const Mask& m, double r, bool dilation) {
  const auto& d = m.grid.dims;
  const Eigen::Vector3d sp = m.grid.spacing_mm();
  std::vector<std::array<int, 3>> features;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if ((m.at(i, j, k) != 0) == dilation) features.push_back({i, j, k});
  Mask out(m.grid, 0);
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        bool near = false;
        for (const auto& f : features)
          if (Eigen::Vector3d((f[0] - i) * sp[0], (f[1] - j) * sp[1], (f[2] - k) * sp[2]).norm() <= r + 1e-9) {
            near = true;
            break;
          }
        out.at(i, j, k) = dilation ? near : (m.at(i, j, k) && !near);
      }
  return out;
}

// Masks that fill a small part of their grid (dilate and erode work on the
// mask's box grown by the radius), at its edge and away from it, and masks
// that fill the grid.
TEST(Morphology, DilateAndErodeAgreeWithTheDefinitionOnMasksInAPartOfTheGrid) {
  std::uint32_t state = 777;
  auto next = [&state] { return state = state * 1664525u + 1013904223u; };
  const Eigen::Vector3d sp(0.9, 1.1, 2.5);
  struct Part { std::array<int, 3> lo, hi; };
  for (const Part part : {Part{{8, 6, 3}, {13, 10, 6}}, Part{{0, 2, 0}, {5, 7, 2}}, Part{{0, 0, 0}, {19, 15, 9}}})
    for (const unsigned percent : {40u, 80u})
      for (const double r : {1.0, 2.6, 4.0}) {
        Mask m(grid({20, 16, 10}, sp), 0);
        for (int k = part.lo[2]; k <= part.hi[2]; ++k)
          for (int j = part.lo[1]; j <= part.hi[1]; ++j)
            for (int i = part.lo[0]; i <= part.hi[0]; ++i) m.at(i, j, k) = (next() >> 8) % 100 < percent;
        EXPECT_EQ(dilate(m, r).voxels, by_definition(m, r, true).voxels) << part.lo[0] << " " << percent << " " << r;
        EXPECT_EQ(erode(m, r).voxels, by_definition(m, r, false).voxels) << part.lo[0] << " " << percent << " " << r;
      }
  const Mask empty(grid({6, 5, 4}), 0);
  EXPECT_EQ(count_nonzero(dilate(empty, 2.0)), 0u);
  EXPECT_EQ(count_nonzero(erode(empty, 2.0)), 0u);
}

// Solid masks (most voxels deep inside, whose distances the dilation and
// erosion take from the mask's boundary alone): a ball and a slab with a
// hole, against the definition.
TEST(Morphology, DilateAndErodeOfSolidMasksAgreeWithTheDefinition) {
  const Eigen::Vector3d sp(0.9, 1.1, 2.5);
  Mask ball(grid({24, 20, 10}, sp), 0), slab(grid({24, 20, 10}, sp), 0);
  for (int k = 0; k < 10; ++k)
    for (int j = 0; j < 20; ++j)
      for (int i = 0; i < 24; ++i) {
        const Eigen::Vector3d x((i - 11.5) * sp[0], (j - 9.5) * sp[1], (k - 4.5) * sp[2]);
        ball.at(i, j, k) = x.norm() < 9.0;
        slab.at(i, j, k) = k >= 2 && k <= 7 && !(std::abs(i - 12) <= 2 && std::abs(j - 10) <= 2 && k == 4);
      }
  for (const Mask* m : {&ball, &slab})
    for (const double r : {1.0, 2.6, 5.5}) {
      EXPECT_EQ(dilate(*m, r).voxels, by_definition(*m, r, true).voxels) << r;
      EXPECT_EQ(erode(*m, r).voxels, by_definition(*m, r, false).voxels) << r;
    }
}

TEST(Morphology, LabelsThresholdAndStats) {
  LabelImage lab(grid({5, 4, 3}, {2, 1, 1}), 0);
  lab.at(1, 1, 1) = 2;
  lab.at(3, 2, 1) = 3;
  lab.at(4, 3, 2) = 7;
  const Mask m = mask_of_labels(lab, {2, 3});
  EXPECT_EQ(count_nonzero(m), 2u);
  EXPECT_DOUBLE_EQ(volume_ml(m), 2 * 2.0 / 1000.0);
  const Eigen::Vector3d c = centroid_mm(m);
  EXPECT_NEAR(c.x(), 4.0, 1e-12);  // voxel x 2 -> 4 mm
  EXPECT_NEAR(c.y(), 1.5, 1e-12);
  const VoxelBox box = bounding_box_voxels(m);
  EXPECT_FALSE(box.empty);
  EXPECT_EQ(box.lo, (std::array<int, 3>{1, 1, 1}));
  EXPECT_EQ(box.hi, (std::array<int, 3>{3, 2, 1}));
  EXPECT_TRUE(bounding_box_voxels(Mask(m.grid, 0)).empty);
  EXPECT_THROW(centroid_mm(Mask(m.grid, 0)), InputError);
  ImageF img(lab.grid, 0.f);
  img.voxels[3] = 5.f;
  img.voxels[4] = 10.f;
  EXPECT_EQ(count_nonzero(threshold(img, 4.f, 6.f)), 1u);
}

}  // namespace
TEST(Morphology, BoundingBoxIsTheExtentOfTheSetVoxels) {
  // Sparse random masks (a few voxels, some rows empty, set voxels at the
  // grid's edges) against the definition: the min and max index per axis.
  std::uint32_t state = 12345;
  const auto next = [&] { return state = state * 1664525u + 1013904223u; };
  for (int trial = 0; trial < 50; ++trial) {
    Mask m(grid({7 + trial % 5, 6, 4 + trial % 3}, {1, 1, 1}), 0);
    const int n = 1 + static_cast<int>(next() % 6);
    for (int s = 0; s < n; ++s) m.voxels[next() % m.voxels.size()] = 1;
    VoxelBox want;
    want.lo = {m.grid.dims[0], m.grid.dims[1], m.grid.dims[2]};
    for (int k = 0; k < m.grid.dims[2]; ++k)
      for (int j = 0; j < m.grid.dims[1]; ++j)
        for (int i = 0; i < m.grid.dims[0]; ++i)
          if (m.at(i, j, k)) {
            want.lo = {std::min(want.lo[0], i), std::min(want.lo[1], j), std::min(want.lo[2], k)};
            want.hi = {std::max(want.hi[0], i), std::max(want.hi[1], j), std::max(want.hi[2], k)};
          }
    const VoxelBox box = bounding_box_voxels(m);
    ASSERT_FALSE(box.empty);
    EXPECT_EQ(box.lo, want.lo) << "trial " << trial;
    EXPECT_EQ(box.hi, want.hi) << "trial " << trial;
  }
}

}  // namespace brainshift
