// Cropping a mask to a box keeps every voxel at its world position.
#include <gtest/gtest.h>

#include "core/errors.h"
#include "image/image_stats.h"

using namespace brainshift;

TEST(Crop, KeepsWorldPositionsAndContent) {
  Grid3 g;
  g.dims = {20, 16, 12};
  g.world_from_voxel << 0, -0.9, 0, 40,  //
      1.1, 0, 0, -20,                    //
      0, 0, 2.5, 7,                      //
      0, 0, 0, 1;
  Mask m(g, 0);
  for (int k = 4; k <= 6; ++k)
    for (int j = 5; j <= 9; ++j)
      for (int i = 3; i <= 8; ++i) m.at(i, j, k) = 1;
  const VoxelBox tight = bounding_box_voxels(m);
  const VoxelBox box = grow_box(tight, g, 2.0);
  // 2 mm is 2 voxels along x (1.1 mm), 3 along y (0.9 mm), 1 along z (2.5 mm).
  EXPECT_EQ(box.lo[0], 1);
  EXPECT_EQ(box.lo[1], 2);
  EXPECT_EQ(box.lo[2], 3);
  EXPECT_EQ(box.hi[0], 10);
  EXPECT_EQ(box.hi[1], 12);
  EXPECT_EQ(box.hi[2], 7);
  const Mask c = crop_to_box(m, box);
  EXPECT_EQ(count_nonzero(c), count_nonzero(m));
  for (int k = 0; k < c.grid.dims[2]; ++k)
    for (int j = 0; j < c.grid.dims[1]; ++j)
      for (int i = 0; i < c.grid.dims[0]; ++i) {
        const int I = i + box.lo[0], J = j + box.lo[1], K = k + box.lo[2];
        ASSERT_EQ(c.at(i, j, k), m.at(I, J, K));
        ASSERT_LT((c.grid.world_mm(i, j, k) - g.world_mm(I, J, K)).norm(), 1e-9);
      }
  // Growing never leaves the grid.
  const VoxelBox huge = grow_box(tight, g, 1000.0);
  EXPECT_EQ(huge.lo, (std::array<int, 3>{0, 0, 0}));
  EXPECT_EQ(huge.hi, (std::array<int, 3>{19, 15, 11}));
  EXPECT_THROW(crop_to_box(m, VoxelBox{}), InputError);
}
