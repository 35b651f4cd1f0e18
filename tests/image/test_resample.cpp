#include <gtest/gtest.h>

#include <stdexcept>
#include <utility>

#include "image/resample.h"

namespace brainshift {
namespace {

Grid3 grid(std::array<int, 3> dims, Eigen::Vector3d spacing, Eigen::Vector3d origin) {
  Grid3 g;
  g.dims = dims;
  g.world_from_voxel.diagonal().head<3>() = spacing;
  g.world_from_voxel.topRightCorner<3, 1>() = origin;
  return g;
}

double linear_fn(const Eigen::Vector3d& p) { return 3.0 + 0.5 * p.x() - 1.25 * p.y() + 0.75 * p.z(); }

ImageF image_of_linear_fn(const Grid3& g) {
  ImageF img(g);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) img.at(i, j, k) = static_cast<float>(linear_fn(g.world_mm(i, j, k)));
  return img;
}

TEST(Resample, IdentityReproducesImage) {
  const Grid3 g = grid({6, 5, 4}, {1.0, 2.0, 0.5}, {-3, 4, 10});
  ImageF img(g);
  LabelImage lab(g);
  for (std::size_t i = 0; i < img.voxels.size(); ++i) {
    img.voxels[i] = static_cast<float>((i * 7919) % 101);
    lab.voxels[i] = static_cast<std::uint16_t>(i % 5);
  }
  EXPECT_EQ(resample_linear(img, g).voxels, img.voxels);
  EXPECT_EQ(resample_nearest(lab, g).voxels, lab.voxels);
}

TEST(Resample, IntegerTranslationShiftsVoxels) {
  const Grid3 g = grid({8, 6, 5}, {1.0, 1.0, 2.0}, {0, 0, 0});
  ImageF img(g);
  LabelImage lab(g);
  for (std::size_t i = 0; i < img.voxels.size(); ++i) {
    img.voxels[i] = static_cast<float>(i);
    lab.voxels[i] = static_cast<std::uint16_t>(i);
  }
  // src world = target world + (2, -1, 2 mm) -> one voxel along z.
  Eigen::Matrix4d shift = Eigen::Matrix4d::Identity();
  shift.topRightCorner<3, 1>() = Eigen::Vector3d(2, -1, 2);
  const ImageF r = resample_linear(img, g, shift, -1.f);
  const LabelImage rl = resample_nearest(lab, g, shift, 999);
  for (int k = 0; k < 5; ++k)
    for (int j = 0; j < 6; ++j)
      for (int i = 0; i < 8; ++i) {
        const bool inside = g.contains(i + 2, j - 1, k + 1);
        EXPECT_EQ(r.at(i, j, k), inside ? img.at(i + 2, j - 1, k + 1) : -1.f);
        EXPECT_EQ(rl.at(i, j, k), inside ? lab.at(i + 2, j - 1, k + 1) : 999);
      }
}

TEST(Resample, TrilinearReproducesLinearFunctionsOnObliqueGrid) {
  const Grid3 src = grid({20, 18, 16}, {1.0, 1.5, 2.0}, {-10, -12, -15});
  const ImageF img = image_of_linear_fn(src);
  Grid3 target;
  target.dims = {9, 8, 7};
  target.world_from_voxel.topLeftCorner<3, 3>() =
      Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix() * 0.8;
  target.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-3, -2, -4);
  const ImageF r = resample_linear(img, target);
  for (int k = 0; k < 7; ++k)
    for (int j = 0; j < 8; ++j)
      for (int i = 0; i < 9; ++i)
        EXPECT_NEAR(r.at(i, j, k), linear_fn(target.world_mm(i, j, k)), 1e-4);
  EXPECT_NEAR(sample_linear(img, Eigen::Vector3d(0.3, -2.7, 1.9), -100.f), linear_fn({0.3, -2.7, 1.9}), 1e-4);
}

TEST(Resample, OutsideValueBeyondHalfVoxel) {
  const Grid3 g = grid({4, 4, 4}, {1, 1, 1}, {0, 0, 0});
  const ImageF img(g, 5.f);
  EXPECT_EQ(sample_linear(img, {-0.4, 1, 1}, -7.f), 5.f);  // within the voxel extent
  EXPECT_EQ(sample_linear(img, {-0.6, 1, 1}, -7.f), -7.f);
  EXPECT_EQ(sample_linear(img, {1, 3.6, 1}, -7.f), -7.f);
  const LabelImage lab(g, 2);
  EXPECT_EQ(sample_nearest(lab, {3.4, 0, 0}, 9), 2);
  EXPECT_EQ(sample_nearest(lab, {3.6, 0, 0}, 9), 9);
}

TEST(Resample, NearestPicksClosestVoxelThroughWorld) {
  // Source at 0.5 mm, target at 1 mm offset by 0.25 mm: nearest source voxel is well defined.
  const Grid3 src = grid({10, 10, 10}, {0.5, 0.5, 0.5}, {0, 0, 0});
  LabelImage lab(src);
  for (int k = 0; k < 10; ++k)
    for (int j = 0; j < 10; ++j)
      for (int i = 0; i < 10; ++i) lab.at(i, j, k) = static_cast<std::uint16_t>(i + 10 * j + 100 * k);
  const Grid3 target = grid({4, 4, 4}, {1, 1, 1}, {0.1, 0.1, 0.1});
  const LabelImage r = resample_nearest(lab, target);
  // world 1.1 -> source index 2.2 -> 2
  EXPECT_EQ(r.at(1, 1, 1), 2 + 10 * 2 + 100 * 2);
  EXPECT_EQ(r.at(3, 0, 2), 6 + 0 + 100 * 4);
}

// A coarser grid of the same extent: the outer faces of the voxel box are the
// same points in world, whatever the number of voxels.
TEST(Resample, TheSameExtentGridSpansTheSameBox) {
  Grid3 g = grid({258, 309, 229}, {0.7, 0.7, 0.7}, {-90, -110, -70});
  g.world_from_voxel.topLeftCorner<3, 3>() =
      Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix() * 0.7;
  const Grid3 c = same_extent_grid(g, {181, 216, 160});
  EXPECT_EQ(c.dims, (std::array<int, 3>{181, 216, 160}));
  for (int corner = 0; corner < 8; ++corner) {
    const Eigen::Vector3d f(corner & 1 ? g.dims[0] - 0.5 : -0.5, corner & 2 ? g.dims[1] - 0.5 : -0.5,
                            corner & 4 ? g.dims[2] - 0.5 : -0.5);
    const Eigen::Vector3d k(corner & 1 ? c.dims[0] - 0.5 : -0.5, corner & 2 ? c.dims[1] - 0.5 : -0.5,
                            corner & 4 ? c.dims[2] - 0.5 : -0.5);
    EXPECT_LT((g.world_mm(f.x(), f.y(), f.z()) - c.world_mm(k.x(), k.y(), k.z())).norm(), 1e-9) << corner;
  }
  EXPECT_NEAR(c.spacing_mm().x(), 0.7 * 258 / 181, 1e-12);
}

// Smoothing to the coarser voxels' profile and sampling keep a linear
// intensity (away from the edges, where the smoothing replicates), and
// average the noise down by about the ratio of the voxel volumes.
TEST(Resample, DownsamplingKeepsALinearIntensityAndAveragesNoise) {
  const Grid3 fine = grid({60, 50, 40}, {0.7, 0.7, 0.7}, {-20, -15, -12});
  const Grid3 coarse = same_extent_grid(fine, {42, 35, 28});
  const ImageF down = downsample_linear(image_of_linear_fn(fine), coarse);
  for (int k = 4; k < coarse.dims[2] - 4; ++k)
    for (int j = 4; j < coarse.dims[1] - 4; ++j)
      for (int i = 4; i < coarse.dims[0] - 4; ++i)
        ASSERT_NEAR(down.at(i, j, k), linear_fn(coarse.world_mm(i, j, k)), 1e-3) << i << " " << j << " " << k;
  ImageF noise(fine);
  std::uint32_t state = 12345;
  for (float& v : noise.voxels) {
    state = state * 1664525u + 1013904223u;
    v = static_cast<float>(state >> 8) / static_cast<float>(1u << 24) - 0.5f;  // sd 0.289
  }
  const ImageF n2 = downsample_linear(noise, coarse);
  double ss = 0;
  std::size_t count = 0;
  for (int k = 4; k < coarse.dims[2] - 4; ++k)
    for (int j = 4; j < coarse.dims[1] - 4; ++j)
      for (int i = 4; i < coarse.dims[0] - 4; ++i, ++count) ss += n2.at(i, j, k) * n2.at(i, j, k);
  const double sd = std::sqrt(ss / static_cast<double>(count));
  EXPECT_LT(sd, 0.289 * 0.75) << "noise finer than the coarser voxels is averaged";
  EXPECT_GT(sd, 0.289 * 0.2) << "but not smoothed away as by a much wider kernel";
}

// A ball of label 1 holding a smaller ball of label 2, on a 1 mm grid.
LabelImage two_balls(const Grid3& g, const Eigen::Vector3d& centre_mm) {
  LabelImage l(g, 0);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const double r = (g.world_mm(i, j, k) - centre_mm).norm();
        l.at(i, j, k) = r < 6.0 ? 2 : r < 15.0 ? 1 : 0;
      }
  return l;
}

// Centroid (mm) and volume (mm^3) of the voxels holding label `value`.
std::pair<Eigen::Vector3d, double> centroid_and_volume(const LabelImage& l, std::uint16_t value) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  double n = 0;
  for (int k = 0; k < l.grid.dims[2]; ++k)
    for (int j = 0; j < l.grid.dims[1]; ++j)
      for (int i = 0; i < l.grid.dims[0]; ++i)
        if (l.at(i, j, k) == value) sum += l.grid.world_mm(i, j, k), n += 1;
  return {sum / n, n * l.grid.spacing_mm().prod()};
}

// Labels taken to a coarser grid keep their place and size, at a whole ratio
// (2:1, where every coarser centre lies halfway between source voxels and
// the nearest-voxel rule moves every outline by half a source voxel along
// each axis) as at a fractional one; a grid of another extent is refused.
TEST(Resample, DownsampledLabelsKeepTheirPlaceAndSize) {
  const Grid3 fine = grid({64, 60, 56}, {1.0, 1.0, 1.0}, {-31.5, -29.5, -27.5});
  const Eigen::Vector3d centre(0.3, -0.4, 0.2);
  const LabelImage labels = two_balls(fine, centre);
  for (const std::array<int, 3> dims : {std::array<int, 3>{32, 30, 28}, std::array<int, 3>{43, 40, 37}}) {
    const Grid3 coarse = same_extent_grid(fine, dims);
    const LabelImage down = downsample_labels(labels, coarse);
    for (std::uint16_t value : {std::uint16_t{1}, std::uint16_t{2}}) {
      const auto [c_fine, v_fine] = centroid_and_volume(labels, value);
      const auto [c_down, v_down] = centroid_and_volume(down, value);
      // Quantisation alone: a few hundredths of a mm for the 15 mm ball, a
      // tenth or two for the 6 mm one (the rule replaced moves both by 0.87).
      EXPECT_LT((c_down - c_fine).norm(), value == 1 ? 0.1 : 0.25) << dims[0] << " label " << value;
      EXPECT_NEAR(v_down / v_fine, 1.0, 0.05) << dims[0] << " label " << value;
    }
  }
  const LabelImage nearest = resample_nearest(labels, same_extent_grid(fine, {32, 30, 28}));
  EXPECT_GT((centroid_and_volume(nearest, 1).first - centroid_and_volume(labels, 1).first).norm(), 0.5)
      << "the rule this replaces, for the record: halves rounded up move the ball";
  Grid3 other = same_extent_grid(fine, {32, 30, 28});
  other.world_from_voxel(0, 3) += 1.0;
  EXPECT_THROW(downsample_labels(labels, other), std::invalid_argument);
}

}  // namespace
}  // namespace brainshift
