// The field module's samplers are the one trilinear sampler
// (image/interpolation.h, TrilinearEdge::kVoxelExtent): warping an image and
// sampling a displacement field give what it gives on the same input, to
// 1e-6 relative, inside, in the outer half voxel and outside.
#include <gtest/gtest.h>

#include <optional>
#include <random>

#include "box_mesh.h"
#include "field/vector_sampling.h"
#include "field/warp.h"
#include "image/interpolation.h"

namespace brainshift {
namespace {

VectorImage3 smooth_field(const Grid3& g) {
  VectorImage3 u(g);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        u.vectors[g.index(i, j, k)] =
            Eigen::Vector3f(2.5f * std::sin(0.4f * j), -1.5f * std::cos(0.3f * k + 0.2f * i), 1.2f * std::sin(0.5f * i));
  return u;
}

TEST(SamplingAgreement, WarpIsTheTrilinearSamplerAtXPlusU) {
  const Grid3 preop_grid = test::oblique_grid({14, 12, 10}, {1.0, 1.2, 1.5}, {-7, -6, -8}, 0.25);
  const Grid3 field_grid = test::oblique_grid({16, 15, 12}, {0.9, 0.9, 1.4}, {-8, -8, -9}, -0.1);
  ImageF preop(preop_grid);
  std::mt19937 rng(21);
  std::uniform_real_distribution<float> value(100.f, 1000.f);
  for (auto& v : preop.voxels) v = value(rng);
  const VectorImage3 u = smooth_field(field_grid);
  const ImageF out = warp_image_linear(preop, u, -5.f);
  const Eigen::Matrix4d preop_voxel_from_world = preop_grid.voxel_from_world();
  int inside = 0;
  for (int k = 0; k < field_grid.dims[2]; ++k)
    for (int j = 0; j < field_grid.dims[1]; ++j)
      for (int i = 0; i < field_grid.dims[0]; ++i) {
        const Eigen::Vector3d p = field_grid.world_mm(i, j, k) + u.vectors[field_grid.index(i, j, k)].cast<double>();
        double expected = 0;
        if (!trilinear_sample<TrilinearEdge::kVoxelExtent>(preop_grid, preop.voxels.data(),
                                                          (preop_voxel_from_world * p.homogeneous()).head<3>().eval(),
                                                          &expected)) {
          ASSERT_EQ(out.at(i, j, k), -5.f) << i << "," << j << "," << k;
          continue;
        }
        ++inside;
        // The warp interpolates in float (it runs per voxel): 1e-6 relative.
        ASSERT_LE(std::abs(out.at(i, j, k) - expected), 1e-6 * expected) << i << "," << j << "," << k;
      }
  EXPECT_GT(inside, 500);
  EXPECT_LT(inside, static_cast<int>(field_grid.voxel_count()));
}

TEST(SamplingAgreement, VectorSamplingIsTheTrilinearSampler) {
  const Grid3 g = test::oblique_grid({9, 8, 7}, {1.1, 0.8, 1.6}, {-3, 2, -4}, 0.4);
  const VectorImage3 u = smooth_field(g);
  const Eigen::Matrix4d voxel_from_world = g.voxel_from_world();
  std::mt19937 rng(22);
  std::uniform_real_distribution<double> coord(-1.5, 9.5);
  int inside = 0;
  for (int n = 0; n < 2000; ++n) {
    const Eigen::Vector3d voxel(coord(rng), coord(rng), coord(rng));
    const Eigen::Vector3d world = g.world_mm(voxel.x(), voxel.y(), voxel.z());
    Eigen::Vector3d expected = Eigen::Vector3d::Zero();
    const bool sampled = trilinear_sample<TrilinearEdge::kVoxelExtent>(
        g, u.vectors.data(), (voxel_from_world * world.homogeneous()).head<3>().eval(), &expected);
    const std::optional<Eigen::Vector3d> by_world = sample_vector_linear(u, world);
    const std::optional<Eigen::Vector3d> by_voxel = sample_vector_linear_voxel(u, voxel);
    ASSERT_EQ(by_world.has_value(), sampled) << voxel.transpose();
    if (!sampled) continue;
    ++inside;
    ASSERT_TRUE(by_voxel.has_value());
    const double scale = std::max(expected.norm(), 1e-3);
    EXPECT_LE((*by_world - expected).norm(), 1e-6 * scale) << voxel.transpose();
    EXPECT_LE((*by_voxel - expected).norm(), 1e-6 * scale) << voxel.transpose();
  }
  EXPECT_GT(inside, 200);
  EXPECT_LT(inside, 2000);
}

// A field resampled onto another grid is the sampler at each of its voxel
// centres, and zero where a centre lies beyond the field.
TEST(SamplingAgreement, ResampledFieldIsTheSamplerAtEachVoxelCentre) {
  const Grid3 g = test::oblique_grid({9, 8, 7}, {1.1, 0.8, 1.6}, {-3, 2, -4}, 0.4);
  const VectorImage3 u = smooth_field(g);
  const Grid3 target = test::oblique_grid({14, 12, 11}, {0.7, 0.6, 1.0}, {-4, 1, -5}, 0.3);
  const VectorImage3 r = resample_vector_linear(u, target);
  ASSERT_TRUE(r.grid.same_geometry(target));
  int inside = 0, outside = 0;
  for (int k = 0; k < target.dims[2]; ++k)
    for (int j = 0; j < target.dims[1]; ++j)
      for (int i = 0; i < target.dims[0]; ++i) {
        const auto expected = sample_vector_linear(u, target.world_mm(i, j, k));
        const Eigen::Vector3d got = r.vectors[target.index(i, j, k)].cast<double>();
        if (!expected) {
          ++outside;
          ASSERT_EQ(got, Eigen::Vector3d::Zero());
          continue;
        }
        ++inside;
        ASSERT_LE((got - *expected).norm(), 1e-5 * std::max(1.0, expected->norm())) << i << "," << j << "," << k;
      }
  EXPECT_GT(inside, 100);
  EXPECT_GT(outside, 100);
}

}  // namespace
}  // namespace brainshift
