// The registration's value-and-gradient sampler is the one trilinear sampler
// (image/interpolation.h, TrilinearEdge::kCentreHull) seen through the
// image's affine: same value to 1e-6 relative, the world gradient is the
// chain rule of the voxel one, nothing outside the hull of voxel centres or
// where a corner is not finite.
#include <gtest/gtest.h>

#include <limits>
#include <random>

#include "image/interpolation.h"
#include "registration/linear_sampler.h"

namespace brainshift {
namespace {

ImageF oblique_random_image() {
  Grid3 g;
  g.dims = {9, 8, 7};
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.35, Eigen::Vector3d(0.2, 1, -0.4).normalized()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = r * Eigen::Vector3d(1.2, 0.8, 1.5).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-5, 4, 1);
  ImageF img(g);
  std::mt19937 rng(31);
  std::uniform_real_distribution<float> value(-50.f, 50.f);  // a distance map's signs
  for (auto& v : img.voxels) v = value(rng);
  return img;
}

TEST(LinearSampler, AgreesWithTheTrilinearSamplerInsideTheHull) {
  const ImageF img = oblique_random_image();
  const LinearSampler sampler(img);
  const Eigen::Matrix4d voxel_from_world = img.grid.voxel_from_world();
  std::mt19937 rng(32);
  std::uniform_real_distribution<double> coord(-1.0, 9.0);
  int inside = 0;
  for (int n = 0; n < 2000; ++n) {
    const Eigen::Vector3d voxel(coord(rng), coord(rng), coord(rng));
    const Eigen::Vector3d world = img.grid.world_mm(voxel.x(), voxel.y(), voxel.z());
    const Eigen::Vector3d v = (voxel_from_world * world.homogeneous()).head<3>();
    TrilinearCell<double> cell;
    const bool in_hull = trilinear_cell<TrilinearEdge::kCentreHull>(img.grid, v, &cell);
    double value = 0, value_only = 0;
    Eigen::Vector3d gradient;
    ASSERT_EQ(sampler.sample(world, &value, &gradient), in_hull) << voxel.transpose();
    if (!in_hull) continue;
    ++inside;
    ASSERT_TRUE(sampler.sample(world, &value_only, nullptr));
    Eigen::Vector3d d_voxel;
    const double expected =
        trilinear_blend_gradient(trilinear_corners<double>(img.voxels.data(), cell), cell, &d_voxel);
    const double scale = std::max(std::abs(expected), 1.0);
    EXPECT_LE(std::abs(value - expected), 1e-6 * scale);
    EXPECT_EQ(value_only, value);
    const Eigen::Vector3d expected_gradient = voxel_from_world.topLeftCorner<3, 3>().transpose() * d_voxel;
    EXPECT_LE((gradient - expected_gradient).norm(), 1e-6 * std::max(expected_gradient.norm(), 1.0));
  }
  EXPECT_GT(inside, 200);
  EXPECT_LT(inside, 2000);
}

// The world gradient is the derivative of the sampled value along world axes.
TEST(LinearSampler, WorldGradientMatchesFiniteDifferences) {
  const ImageF img = oblique_random_image();
  const LinearSampler sampler(img);
  const Eigen::Vector3d x = img.grid.world_mm(3.3, 4.6, 2.2);
  double value;
  Eigen::Vector3d gradient;
  ASSERT_TRUE(sampler.sample(x, &value, &gradient));
  const double h = 1e-6;
  for (int a = 0; a < 3; ++a) {
    double up, down;
    ASSERT_TRUE(sampler.sample(x + h * Eigen::Vector3d::Unit(a), &up, nullptr));
    ASSERT_TRUE(sampler.sample(x - h * Eigen::Vector3d::Unit(a), &down, nullptr));
    EXPECT_NEAR(gradient[a], (up - down) / (2 * h), 1e-4) << a;
  }
}

TEST(LinearSampler, NonFiniteCornerIsNoData) {
  ImageF img = oblique_random_image();
  img.at(4, 4, 3) = std::numeric_limits<float>::infinity();
  const LinearSampler sampler(img);
  double value = 123;
  Eigen::Vector3d gradient(1, 2, 3);
  EXPECT_FALSE(sampler.sample(img.grid.world_mm(3.5, 3.5, 2.5), &value, &gradient));  // the cell has it as a corner
  EXPECT_EQ(value, 123);
  EXPECT_EQ(gradient, Eigen::Vector3d(1, 2, 3));
  EXPECT_TRUE(sampler.sample(img.grid.world_mm(1.5, 1.5, 1.5), &value, &gradient));  // a cell away
}

}  // namespace
}  // namespace brainshift
