// The uncertainty map's two parts on cases with a known answer.
#include <gtest/gtest.h>

#include <cmath>

#include "box_mesh.h"  // tests/fem
#include "quality/uncertainty_map.h"

using namespace brainshift;

TEST(SurfaceNoise, PropagatedThroughTheIdentityKeepsItsRms) {
  // Nodes spread over 400 mm: many correlation lengths, so the average over
  // nodes of the estimated variance is close to its expectation.
  std::vector<Eigen::Vector3d> points;
  std::vector<double> sigma;
  for (int i = 0; i < 2000; ++i) {
    points.emplace_back(0.2 * i, std::fmod(7.3 * i, 100.0), std::fmod(3.1 * i, 60.0));
    sigma.push_back(i % 2 ? 1.0 : 2.0);
  }
  UncertaintyParameters p;
  p.samples = 64;
  const auto rms = propagate_surface_noise(points, sigma, [](const std::vector<Eigen::Vector3d>& v) { return v; }, p);
  ASSERT_EQ(rms.size(), points.size());
  double even = 0, odd = 0;
  for (std::size_t i = 0; i < rms.size(); ++i) (i % 2 ? odd : even) += rms[i] * rms[i] / 1000.0;
  EXPECT_NEAR(std::sqrt(even), 2.0, 0.2);
  EXPECT_NEAR(std::sqrt(odd), 1.0, 0.1);
}

TEST(SurfaceNoise, IsTheSameForTheSameSeed) {
  std::vector<Eigen::Vector3d> points{{0, 0, 0}, {10, 0, 0}};
  const auto id = [](const std::vector<Eigen::Vector3d>& v) { return v; };
  EXPECT_EQ(propagate_surface_noise(points, {1, 1}, id, {}), propagate_surface_noise(points, {1, 1}, id, {}));
}

namespace {

struct Case {
  test::BoxMesh box = test::make_box_mesh({8, 8, 8}, {-40, -40, -40}, {80, 80, 80});
  LabelImage labels;
  VectorImage3 field;
  Case() {
    Grid3 g;
    g.dims = {40, 40, 20};
    g.world_from_voxel.topLeftCorner<3, 3>() = Eigen::Vector3d(2, 2, 4).asDiagonal();
    g.world_from_voxel.block<3, 1>(0, 3) = Eigen::Vector3d(-39, -39, -38);
    labels = LabelImage(g, 0);
    for (int k = 0; k < 20; ++k)
      for (int j = 0; j < 40; ++j)
        for (int i = 0; i < 40; ++i) labels.at(i, j, k) = g.world_mm(i, j, k).norm() < 30 ? 1 : 0;
    field = VectorImage3(g);
  }
};

}  // namespace

TEST(UncertaintyBand, NoNoiseAndNoShiftIsZeroConstantNoiseIsItsBand) {
  Case c;
  const std::vector<double> none(c.box.mesh.node_count(), 0.0);
  nlohmann::json summary;
  const ImageF zero = uncertainty_band_mm({c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, {1}}, {}, &summary);
  for (float v : zero.voxels) ASSERT_EQ(v, 0.f);
  const std::vector<double> one(c.box.mesh.node_count(), 1.0);
  const ImageF band = uncertainty_band_mm({c.box.mesh, one, c.field, Eigen::Matrix4d::Identity(), c.labels, {1}}, {}, &summary);
  const Grid3& g = c.labels.grid;
  for (std::size_t v = 0; v < band.voxels.size(); ++v) {
    const double r = g.world_mm(v % 40, (v / 40) % 40, v / 1600).norm();
    // One voxel (4 mm) beyond the outline is still the brain's.
    if (r > 30 + 4 * std::sqrt(3.0) + 0.1) ASSERT_EQ(band.voxels[v], 0.f) << "outside the brain no band is claimed";
    if (c.labels.voxels[v] != 0) ASSERT_NEAR(band.voxels[v], kBand95PerRms, 1e-3);
  }
  EXPECT_NEAR(summary["band95_mm"]["mean"].get<double>(), kBand95PerRms, 1e-3);
}

TEST(UncertaintyBand, ModelErrorGrowsWithDepthAndWithTheShift) {
  Case c;
  // A uniform 4 mm non-rigid shift (pull-back), no surface noise.
  for (auto& v : c.field.vectors) v = Eigen::Vector3f(0, 0, 4);
  const std::vector<double> none(c.box.mesh.node_count(), 0.0);
  UncertaintyParameters p;
  const ImageF band = uncertainty_band_mm({c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, {1}}, p);
  const auto at = [&](const Eigen::Vector3d& x) {
    const Eigen::Vector3d v = (c.labels.grid.voxel_from_world() * x.homogeneous()).head<3>();
    return band.at(static_cast<int>(std::lround(v.x())), static_cast<int>(std::lround(v.y())), static_cast<int>(std::lround(v.z())));
  };
  const float centre = at({1, 1, 2}), near_surface = at({27, 1, 2});
  EXPECT_GT(centre, near_surface);
  // Deep inside (29 mm from the outline): the full fraction of the shift.
  EXPECT_NEAR(centre, kBand95PerRms * p.model_error_fraction * 4 * (1 - std::exp(-28.0 / p.depth_scale_mm)), 0.25);
}
