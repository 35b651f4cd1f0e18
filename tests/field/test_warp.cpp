// Warping with a pull-back field: translations shift images exactly, linear
// images are reproduced by trilinear sampling, outside points get the fill value.
#include <gtest/gtest.h>

#include <cstdio>
#include <random>

#include "box_mesh.h"
#include "core/errors.h"
#include "core/timer.h"
#include "field/warp.h"

namespace brainshift {
namespace {

Grid3 unit_grid(std::array<int, 3> dims) {
  Grid3 g;
  g.dims = dims;
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-10, 5, 2);
  return g;
}

VectorImage3 constant_field(const Grid3& g, const Eigen::Vector3f& t) {
  VectorImage3 f(g);
  std::fill(f.vectors.begin(), f.vectors.end(), t);
  return f;
}

TEST(Warp, IntegerTranslationShiftsImageExactly) {
  const Grid3 g = unit_grid({20, 18, 16});
  ImageF img(g);
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> dist(0.f, 100.f);
  for (auto& v : img.voxels) v = dist(rng);
  const Eigen::Vector3f t(2, -3, 5);  // mm == voxels on this grid
  const ImageF out = warp_image_linear(img, constant_field(g, t), -1.f);
  for (int k = 0; k < 16; ++k)
    for (int j = 0; j < 18; ++j)
      for (int i = 0; i < 20; ++i) {
        const int si = i + 2, sj = j - 3, sk = k + 5;
        const float expected = g.contains(si, sj, sk) ? img.at(si, sj, sk) : -1.f;
        ASSERT_FLOAT_EQ(out.at(i, j, k), expected) << i << "," << j << "," << k;
      }
}

TEST(Warp, LabelsFollowIntegerTranslation) {
  const Grid3 g = unit_grid({12, 10, 8});
  LabelImage labels(g);
  for (std::size_t v = 0; v < labels.voxels.size(); ++v) labels.voxels[v] = static_cast<std::uint16_t>(v % 5);
  const LabelImage out = warp_labels_nearest(labels, constant_field(g, Eigen::Vector3f(-1, 2, 1)), 9);
  for (int k = 0; k < 8; ++k)
    for (int j = 0; j < 10; ++j)
      for (int i = 0; i < 12; ++i) {
        const int si = i - 1, sj = j + 2, sk = k + 1;
        ASSERT_EQ(out.at(i, j, k), g.contains(si, sj, sk) ? labels.at(si, sj, sk) : 9);
      }
}

// Different grids for preop and field, sub-voxel translation: a linear image
// is reproduced exactly by trilinear interpolation.
TEST(Warp, SubvoxelTranslationOfLinearImageAcrossGrids) {
  const Grid3 preop_grid = test::oblique_grid({40, 40, 30}, Eigen::Vector3d(1.0, 1.0, 1.5),
                                              Eigen::Vector3d(-20, -25, -20), 0.2);
  const Grid3 field_grid = test::oblique_grid({20, 20, 10}, Eigen::Vector3d(0.9, 0.9, 2.0),
                                              Eigen::Vector3d(-8, -8, -8), -0.1);
  const Eigen::Vector3d a(0.5, -1.25, 2.0);
  const auto f = [&](const Eigen::Vector3d& x) { return a.dot(x) + 7.0; };
  ImageF img(preop_grid);
  for (int k = 0; k < 30; ++k)
    for (int j = 0; j < 40; ++j)
      for (int i = 0; i < 40; ++i) img.at(i, j, k) = static_cast<float>(f(preop_grid.world_mm(i, j, k)));
  const Eigen::Vector3f t(0.37f, -1.61f, 0.93f);
  const ImageF out = warp_image_linear(img, constant_field(field_grid, t));
  for (int k = 0; k < 10; ++k)
    for (int j = 0; j < 20; ++j)
      for (int i = 0; i < 20; ++i) {
        const Eigen::Vector3d p = field_grid.world_mm(i, j, k) + t.cast<double>();
        ASSERT_NEAR(out.at(i, j, k), f(p), 2e-4);
      }
}

TEST(Warp, RejectsFieldWithWrongVectorCount) {
  const Grid3 g = unit_grid({4, 4, 4});
  VectorImage3 f(g);
  f.vectors.pop_back();
  EXPECT_THROW(warp_image_linear(ImageF(g), f), InputError);
  EXPECT_THROW(warp_labels_nearest(LabelImage(g), f), InputError);
}

TEST(Warp, IntraopSizedTiming) {
  const Grid3 field_grid = test::oblique_grid({256, 256, 60}, Eigen::Vector3d(0.94, 0.94, 2.5),
                                              Eigen::Vector3d(-120, -120, -75), 0.1);
  Grid3 preop_grid;
  preop_grid.dims = {181, 217, 181};
  preop_grid.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-90, -126, -72);
  ImageF img(preop_grid, 1.f);
  LabelImage labels(preop_grid, 1);
  VectorImage3 u(field_grid);
  for (std::size_t v = 0; v < u.vectors.size(); ++v) u.vectors[v] = Eigen::Vector3f(0.3f, -0.2f, float(v % 7));
  Stopwatch sw;
  const ImageF out = warp_image_linear(img, u);
  const double linear_s = sw.lap();
  const LabelImage out_labels = warp_labels_nearest(labels, u);
  const double nearest_s = sw.lap();
  std::printf("warp 256x256x60: linear %.3f s, nearest %.3f s\n", linear_s, nearest_s);
  EXPECT_EQ(out.voxels.size(), field_grid.voxel_count());
  EXPECT_EQ(out_labels.voxels.size(), field_grid.voxel_count());
  // The times are printed above; speed goals live in the benchmarks.
}

}  // namespace
}  // namespace brainshift
