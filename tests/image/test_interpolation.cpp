// The one trilinear sampler (image/interpolation.h): exact on linear data,
// the voxel values at voxel centres, each edge rule as documented, and the
// image module's world-space callers (GridSampler, sample_linear,
// resample_linear) agreeing with it.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <optional>
#include <random>

#include "image/interpolation.h"
#include "image/resample.h"

namespace brainshift {
namespace {

constexpr auto kExtent = TrilinearEdge::kVoxelExtent;
constexpr auto kHull = TrilinearEdge::kCentreHull;
constexpr auto kClamp = TrilinearEdge::kClamp;

Grid3 voxel_grid(std::array<int, 3> dims) {
  Grid3 g;
  g.dims = dims;
  return g;
}

// An oblique, anisotropic grid: the callers' world-to-voxel maps are exercised too.
Grid3 oblique_grid(std::array<int, 3> dims, const Eigen::Vector3d& origin_mm) {
  Grid3 g = voxel_grid(dims);
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, -2, 0.5).normalized()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = r * Eigen::Vector3d(1.1, 0.9, 1.7).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = origin_mm;
  return g;
}

double linear_fn(const Eigen::Vector3d& v) { return 40.0 + 2.5 * v.x() - 1.75 * v.y() + 3.25 * v.z(); }

ImageF linear_image(const Grid3& g) {
  ImageF img(g);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) img.at(i, j, k) = static_cast<float>(linear_fn({1.0 * i, 1.0 * j, 1.0 * k}));
  return img;
}

ImageF random_image(const Grid3& g, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> value(100.f, 1000.f);
  ImageF img(g);
  for (auto& v : img.voxels) v = value(rng);
  return img;
}

template <TrilinearEdge Edge, class Real = double>
std::optional<Real> at(const ImageF& img, const Eigen::Vector3d& v) {
  Real value;
  if (!trilinear_sample<Edge, Real>(img.grid, img.voxels.data(), v, &value)) return std::nullopt;
  return value;
}

TEST(Trilinear, ExactOnALinearFunctionInside) {
  const ImageF img = linear_image(voxel_grid({5, 6, 7}));
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> x(0, 4), y(0, 5), z(0, 6);
  for (int n = 0; n < 500; ++n) {
    const Eigen::Vector3d v(x(rng), y(rng), z(rng));
    const double expected = linear_fn(v);
    ASSERT_NEAR(*at<kExtent>(img, v), expected, 1e-9 * std::abs(expected)) << v.transpose();
    ASSERT_NEAR(*at<kHull>(img, v), expected, 1e-9 * std::abs(expected)) << v.transpose();
    ASSERT_NEAR(*at<kClamp>(img, v), expected, 1e-9 * std::abs(expected)) << v.transpose();
    ASSERT_NEAR((*at<kExtent, float>(img, v)), expected, 1e-5 * std::abs(expected)) << v.transpose();
  }
}

TEST(Trilinear, GradientIsTheLinearFunctionsSlope) {
  const ImageF img = linear_image(voxel_grid({5, 6, 7}));
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> x(0, 4), y(0, 5), z(0, 6);
  for (int n = 0; n < 200; ++n) {
    const Eigen::Vector3d v(x(rng), y(rng), z(rng));
    TrilinearCell<double> cell;
    ASSERT_TRUE(trilinear_cell<kHull>(img.grid, v, &cell));
    Eigen::Vector3d d;
    const double value = trilinear_blend_gradient(trilinear_corners<double>(img.voxels.data(), cell), cell, &d);
    EXPECT_NEAR(value, linear_fn(v), 1e-9 * std::abs(linear_fn(v)));
    EXPECT_NEAR(d.x(), 2.5, 1e-9);
    EXPECT_NEAR(d.y(), -1.75, 1e-9);
    EXPECT_NEAR(d.z(), 3.25, 1e-9);
  }
}

// On arbitrary data the gradient is the derivative of the interpolant itself.
TEST(Trilinear, GradientMatchesFiniteDifferencesOfTheValue) {
  const ImageF img = random_image(voxel_grid({4, 5, 3}), 5);
  const Eigen::Vector3d v(1.3, 2.6, 0.45);
  TrilinearCell<double> cell;
  ASSERT_TRUE(trilinear_cell<kHull>(img.grid, v, &cell));
  Eigen::Vector3d d;
  trilinear_blend_gradient(trilinear_corners<double>(img.voxels.data(), cell), cell, &d);
  const double h = 1e-6;
  for (int a = 0; a < 3; ++a) {
    const Eigen::Vector3d step = h * Eigen::Vector3d::Unit(a);
    EXPECT_NEAR(d[a], (*at<kHull>(img, v + step) - *at<kHull>(img, v - step)) / (2 * h), 1e-4) << a;
  }
}

TEST(Trilinear, VoxelCentresGiveTheVoxelValues) {
  const ImageF img = random_image(voxel_grid({4, 3, 5}), 6);
  VectorImage3 field(img.grid);
  for (std::size_t n = 0; n < field.vectors.size(); ++n)
    field.vectors[n] = Eigen::Vector3f(img.voxels[n], -img.voxels[n], 0.5f * img.voxels[n]);
  for (int k = 0; k < 5; ++k)
    for (int j = 0; j < 3; ++j)
      for (int i = 0; i < 4; ++i) {
        const Eigen::Vector3d v(i, j, k);
        const float expected = img.at(i, j, k);
        // Exactly: every centre is a cell's low corner under kVoxelExtent.
        ASSERT_EQ(*at<kExtent>(img, v), expected);
        ASSERT_EQ((*at<kExtent, float>(img, v)), expected);
        Eigen::Vector3d u;
        ASSERT_TRUE(trilinear_sample<kExtent>(field.grid, field.vectors.data(), v, &u));
        ASSERT_EQ(u, field.vectors[field.grid.index(i, j, k)].cast<double>());
        // The whole-cell rules take the last centre as a far corner (t = 1): to rounding.
        ASSERT_NEAR(*at<kHull>(img, v), expected, 1e-12 * expected);
        ASSERT_NEAR(*at<kClamp>(img, v), expected, 1e-12 * expected);
        Eigen::Vector3f uf;
        ASSERT_TRUE((trilinear_sample<kClamp, float>(field.grid, field.vectors.data(), v.cast<float>().eval(), &uf)));
        ASSERT_LE((uf - field.vectors[field.grid.index(i, j, k)]).norm(), 1e-6f * expected);
      }
}

TEST(Trilinear, VoxelExtentReplicatesTheOuterHalfVoxelAndStopsThere) {
  const ImageF img = random_image(voxel_grid({4, 3, 5}), 7);
  // Within half a voxel outside the centres: the edge's value, along each axis.
  EXPECT_EQ(*at<kExtent>(img, {-0.4, 1, 2}), img.at(0, 1, 2));
  EXPECT_EQ(*at<kExtent>(img, {-0.5, 1, 2}), img.at(0, 1, 2));
  EXPECT_EQ(*at<kExtent>(img, {3.5, 1, 2}), img.at(3, 1, 2));
  EXPECT_EQ(*at<kExtent>(img, {1, -0.3, 2}), img.at(1, 0, 2));
  EXPECT_EQ(*at<kExtent>(img, {1, 1, 4.49}), img.at(1, 1, 4));
  // Between edge voxels, still interpolated along the other axes.
  EXPECT_NEAR(*at<kExtent>(img, {-0.2, 0.5, 2}), 0.5 * (img.at(0, 0, 2) + img.at(0, 1, 2)), 1e-4);
  // Farther out, or not a number: nothing is sampled.
  EXPECT_FALSE(at<kExtent>(img, {-0.51, 1, 2}));
  EXPECT_FALSE(at<kExtent>(img, {3.51, 1, 2}));
  EXPECT_FALSE(at<kExtent>(img, {1, 2.6, 2}));
  EXPECT_FALSE(at<kExtent>(img, {1, 1, -0.7}));
  EXPECT_FALSE(at<kExtent>(img, {std::numeric_limits<double>::quiet_NaN(), 1, 2}));
  // A single voxel along an axis is its whole extent.
  const ImageF thin = random_image(voxel_grid({3, 1, 2}), 8);
  EXPECT_EQ(*at<kExtent>(thin, {1, 0.4, 0}), thin.at(1, 0, 0));
  EXPECT_FALSE(at<kExtent>(thin, {1, 0.6, 0}));
}

TEST(Trilinear, CentreHullSamplesOnlyWholeCells) {
  const ImageF img = random_image(voxel_grid({4, 3, 5}), 9);
  EXPECT_EQ(*at<kHull>(img, {0, 0, 0}), img.at(0, 0, 0));
  EXPECT_DOUBLE_EQ(*at<kHull>(img, {3, 2, 4}), img.at(3, 2, 4));  // the far faces belong to the last cells
  EXPECT_FALSE(at<kHull>(img, {-0.01, 1, 1}));
  EXPECT_FALSE(at<kHull>(img, {3.01, 1, 1}));
  EXPECT_FALSE(at<kHull>(img, {1, 1, 4.2}));
  EXPECT_FALSE(at<kHull>(img, {1, std::numeric_limits<double>::quiet_NaN(), 1}));
  // One voxel along an axis: no cell at all.
  EXPECT_FALSE(at<kHull>(random_image(voxel_grid({3, 1, 2}), 10), {1, 0, 0}));
  // Where kVoxelExtent replicates, the hull samples nothing.
  EXPECT_TRUE(at<kExtent>(img, {-0.3, 1, 1}));
}

TEST(Trilinear, ClampSamplesEverywhereAtTheNearestHullPoint) {
  const ImageF img = random_image(voxel_grid({4, 3, 5}), 11);
  EXPECT_EQ(*at<kClamp>(img, {-3, 1.5, 9}), *at<kClamp>(img, {0, 1.5, 4}));
  EXPECT_EQ(*at<kClamp>(img, {7, -2, 2.25}), *at<kClamp>(img, {3, 0, 2.25}));
  EXPECT_EQ(*at<kClamp>(img, {-1e6, -1e6, -1e6}), img.at(0, 0, 0));
  EXPECT_DOUBLE_EQ(*at<kClamp>(img, {1e6, 1e6, 1e6}), img.at(3, 2, 4));
}

TEST(Trilinear, NearestRoundsHalfUpWithinTheExtent) {
  const Grid3 g = voxel_grid({4, 3, 5});
  std::size_t index = 0;
  ASSERT_TRUE(nearest_voxel(g, {1.5, 0.49, 2.51}, &index));
  EXPECT_EQ(index, g.index(2, 0, 3));
  ASSERT_TRUE(nearest_voxel(g, {-0.5, 2.5, 4.4}, &index));
  EXPECT_EQ(index, g.index(0, 2, 4));
  EXPECT_FALSE(nearest_voxel(g, {-0.51, 1, 1}, &index));
  EXPECT_FALSE(nearest_voxel(g, {1, 1, 4.6}, &index));
  EXPECT_FALSE(nearest_voxel(g, {1, std::numeric_limits<double>::quiet_NaN(), 1}, &index));
}

// |a - b| <= 1e-6 |b|, or both outside.
void expect_agrees(float caller, const std::optional<double>& sampler, float outside, const char* what) {
  if (!sampler) {
    EXPECT_EQ(caller, outside) << what;
    return;
  }
  EXPECT_LE(std::abs(caller - *sampler), 1e-6 * std::abs(*sampler)) << what;
}

TEST(Trilinear, WorldSpaceSamplersAgreeWithIt) {
  const ImageF img = random_image(oblique_grid({9, 8, 7}, {-4, 3, 2}), 12);
  const Eigen::Matrix4d voxel_from_world = img.grid.voxel_from_world();
  const GridSampler sampler(img.grid);
  std::mt19937 rng(13);
  std::uniform_real_distribution<double> coord(-1.5, 10.5);  // inside, the outer half voxel and outside
  int inside = 0, outside = 0;
  for (int n = 0; n < 2000; ++n) {
    const Eigen::Vector3d voxel(coord(rng), coord(rng), coord(rng));
    const Eigen::Vector3d world = img.grid.world_mm(voxel.x(), voxel.y(), voxel.z());
    const auto expected = at<kExtent>(img, (voxel_from_world * world.homogeneous()).head<3>());
    (expected ? inside : outside)++;
    expect_agrees(sample_linear(img, world, -5.f), expected, -5.f, "sample_linear");
    expect_agrees(sampler.linear(img.voxels, world, -5.f), expected, -5.f, "GridSampler");
  }
  EXPECT_GT(inside, 200);
  EXPECT_GT(outside, 200);
}

TEST(Trilinear, ResamplingAgreesWithIt) {
  const ImageF src = random_image(oblique_grid({9, 8, 7}, {-4, 3, 2}), 14);
  const Grid3 target = oblique_grid({12, 11, 10}, {-7, 1, 0});
  Eigen::Matrix4d src_from_target = Eigen::Matrix4d::Identity();
  src_from_target.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  src_from_target.topRightCorner<3, 1>() = Eigen::Vector3d(0.7, -0.4, 1.1);
  const ImageF out = resample_linear(src, target, src_from_target, -5.f);
  const Eigen::Matrix4d m = src.grid.voxel_from_world() * src_from_target * target.world_from_voxel;
  int inside = 0;
  for (int k = 0; k < target.dims[2]; ++k)
    for (int j = 0; j < target.dims[1]; ++j)
      for (int i = 0; i < target.dims[0]; ++i) {
        const auto expected = at<kExtent>(src, (m * Eigen::Vector4d(i, j, k, 1)).head<3>());
        inside += expected.has_value();
        expect_agrees(out.at(i, j, k), expected, -5.f, "resample_linear");
      }
  EXPECT_GT(inside, 100);
  EXPECT_LT(inside, static_cast<int>(target.voxel_count()));
}

}  // namespace
}  // namespace brainshift
