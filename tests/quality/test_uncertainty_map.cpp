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

TEST(UncertaintyBand, WithoutShiftOrResidualItIsTheQuantisationAndNoiseAddsInQuadrature) {
  Case c;
  const double q = std::cbrt(2.0 * 2.0 * 4.0) / std::sqrt(12.0);  // the 2 x 2 x 4 mm voxel
  const std::vector<double> none(c.box.mesh.node_count(), 0.0);
  nlohmann::json summary;
  const ImageF floor = uncertainty_band_mm({c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, false}, {}, &summary);
  const std::vector<double> one(c.box.mesh.node_count(), 1.0);
  const ImageF band = uncertainty_band_mm({c.box.mesh, one, c.field, Eigen::Matrix4d::Identity(), c.labels, false}, {});
  const Grid3& g = c.labels.grid;
  for (std::size_t v = 0; v < band.voxels.size(); ++v) {
    const double r = g.world_mm(v % 40, (v / 40) % 40, v / 1600).norm();
    // One voxel (4 mm) beyond the outline is still the brain's.
    if (r > 30 + 4 * std::sqrt(3.0) + 0.1) {
      ASSERT_EQ(band.voxels[v], 0.f) << "outside the brain no band is claimed";
    }
    if (c.labels.voxels[v] == 0) continue;
    ASSERT_NEAR(floor.voxels[v], kBand95PerRms * q, 1e-3);
    ASSERT_NEAR(band.voxels[v], kBand95PerRms * std::sqrt(1 + q * q), 1e-3);
  }
  EXPECT_NEAR(summary["band95_mm"]["mean"].get<double>(), kBand95PerRms * q, 1e-3);
}

// The answer's warped preop brain is claimed too: a segmentation that falls
// short of it (an image-only one a few mm inside the cortex) does not leave
// the brain it missed at 0, which reads as "certain" on a colour scale.
TEST(UncertaintyBand, WhereTheWarpedPreopPutsBrainTheBandIsClaimedThere) {
  Case c;
  const Grid3& g = c.labels.grid;
  LabelImage warped(g, 0);
  for (std::size_t v = 0; v < warped.voxels.size(); ++v)
    warped.voxels[v] = g.world_mm(v % 40, (v / 40) % 40, v / 1600).norm() < 40 ? 1 : 0;
  const std::vector<double> none(c.box.mesh.node_count(), 0.0);
  const ImageF alone = uncertainty_band_mm({c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, false}, {});
  const ImageF with = uncertainty_band_mm(
      {c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, false, &warped}, {});
  const double q = std::cbrt(2.0 * 2.0 * 4.0) / std::sqrt(12.0);
  std::size_t between = 0;
  for (std::size_t v = 0; v < with.voxels.size(); ++v) {
    const double r = g.world_mm(v % 40, (v / 40) % 40, v / 1600).norm();
    if (c.labels.voxels[v] != 0) {
      ASSERT_EQ(with.voxels[v], alone.voxels[v]);
    }
    if (r < 30 + 4 * std::sqrt(3.0) + 0.1 || r > 39) continue;  // beyond the segmentation's voxel, inside the warped brain
    ++between;
    ASSERT_EQ(alone.voxels[v], 0.f);
    ASSERT_NEAR(with.voxels[v], kBand95PerRms * q, 1e-3);
  }
  EXPECT_GT(between, 1000u);
}

TEST(UncertaintyBand, AUniformShiftAddsNothingAShearGrowsWithDisplacementAndStrain) {
  Case c;
  const std::vector<double> none(c.box.mesh.node_count(), 0.0);
  UncertaintyParameters p;
  const double q = std::cbrt(2.0 * 2.0 * 4.0) / std::sqrt(12.0);
  const auto band_at = [&](const ImageF& band, const Eigen::Vector3d& x) {
    const Eigen::Vector3d v = (c.labels.grid.voxel_from_world() * x.homogeneous()).head<3>();
    return band.at(static_cast<int>(std::lround(v.x())), static_cast<int>(std::lround(v.y())), static_cast<int>(std::lround(v.z())));
  };
  // A uniform 4 mm non-rigid shift: pinned by the data next to it, no model error.
  for (auto& v : c.field.vectors) v = Eigen::Vector3f(0, 0, 4);
  const ImageF uniform = uncertainty_band_mm({c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, false}, p);
  EXPECT_NEAR(band_at(uniform, {1, 1, 2}), kBand95PerRms * q, 1e-3);
  // A shear r = (0, 0, eps x): |r| = eps |x|, |grad r| = eps, so the model's
  // RMS is eps sqrt(|x| resolution).
  const double eps = 0.1;
  const Grid3& g = c.field.grid;
  for (std::size_t v = 0; v < c.field.vectors.size(); ++v)
    c.field.vectors[v] = Eigen::Vector3f(0, 0, static_cast<float>(eps * g.world_mm(v % 40, (v / 40) % 40, v / 1600).x()));
  const ImageF shear = uncertainty_band_mm({c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, false}, p);
  const ImageF refined = uncertainty_band_mm({c.box.mesh, none, c.field, Eigen::Matrix4d::Identity(), c.labels, true}, p);
  for (double x : {5.0, 13.0, 21.0}) {
    const double model = eps * std::sqrt(x * p.resolution_mm);
    // The map is made on a 3 mm grid and interpolated: |x| is known to about 1.5 mm there.
    EXPECT_NEAR(band_at(shear, {x, 1, 2}), kBand95PerRms * std::hypot(q, model), 0.12) << x;
    EXPECT_NEAR(band_at(refined, {x, 1, 2}), kBand95PerRms * std::hypot(q, p.image_residual_fraction * model), 0.12) << x;
  }
  EXPECT_GT(band_at(shear, {21, 1, 2}), band_at(shear, {5, 1, 2}));
}

TEST(UncertaintyBand, ModelErrorIsTheGeometricMeanOfDisplacementAndItsChangeOverTheResolution) {
  UncertaintyParameters p;
  p.resolution_mm = 8;
  EXPECT_DOUBLE_EQ(model_error_rms_mm(2.0, 0.25, p), 2.0);  // sqrt(2 * 8 * 0.25)
  EXPECT_DOUBLE_EQ(model_error_rms_mm(5.0, 0.0, p), 0.0);
  EXPECT_DOUBLE_EQ(model_error_rms_mm(0.0, 0.3, p), 0.0);
}

// Term 3: brain surface out of view. The solve is the identity (each fixed
// node's value is its own displacement) or a known linear map, so the band
// at each node is what the unseen shift there allows.
TEST(UnseenSurface, NothingUnseenNeedsNoSolveAndAddsNothing) {
  bool solved = false;
  const auto solve = [&](const std::vector<Eigen::Vector3d>& v) {
    solved = true;
    return v;
  };
  EXPECT_TRUE(unseen_surface_rms_mm({{0, 0, 0}, {5, 0, 0}}, {false, false}, solve, {}).empty());
  EXPECT_FALSE(solved);
}

TEST(UnseenSurface, AnUnseenNodeMayHaveMovedItsDistanceFromTheSeenSurfaceUpToTheLargestShift) {
  // Seen nodes along x in [0, 10] mm; unseen ones 3, 12 and 45 mm beyond.
  std::vector<Eigen::Vector3d> points;
  std::vector<bool> unseen;
  for (int i = 0; i <= 10; ++i) points.emplace_back(i, 0, 0), unseen.push_back(false);
  for (double x : {13.0, 22.0, 55.0}) points.emplace_back(x, 0, 0), unseen.push_back(true);
  const auto id = [](const std::vector<Eigen::Vector3d>& v) { return v; };
  UncertaintyParameters p;
  const auto rms = unseen_surface_rms_mm(points, unseen, id, p);
  ASSERT_EQ(rms.size(), points.size());
  for (int i = 0; i <= 10; ++i) EXPECT_EQ(rms[i], 0.0);
  EXPECT_NEAR(kBand95PerRms * rms[11], 3.0, 1e-9);
  EXPECT_NEAR(kBand95PerRms * rms[12], 12.0, 1e-9);
  EXPECT_NEAR(kBand95PerRms * rms[13], p.unseen_shift_mm, 1e-9);
  p.unseen_shift_mm = 8;
  EXPECT_NEAR(kBand95PerRms * unseen_surface_rms_mm(points, unseen, id, p)[12], 8.0, 1e-9);
}

TEST(UnseenSurface, TheBandTakesTheWorstDirectionOfTheUnseenShift) {
  // A model that passes a shift along y at 3x and along x, z at half: the
  // band is the y response, whichever direction the data would have chosen.
  const std::vector<Eigen::Vector3d> points{{0, 0, 0}, {4, 0, 0}};
  const auto solve = [](const std::vector<Eigen::Vector3d>& v) {
    std::vector<Eigen::Vector3d> out;
    for (const auto& x : v) out.emplace_back(0.5 * x.x(), 3.0 * x.y(), 0.5 * x.z());
    return out;
  };
  const auto rms = unseen_surface_rms_mm(points, {false, true}, solve, {});
  EXPECT_NEAR(kBand95PerRms * rms[1], 12.0, 1e-9);
  EXPECT_EQ(rms[0], 0.0);
}
