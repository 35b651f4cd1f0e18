// Metrics against analytic answers: offset spheres (Dice, surface distances),
// linear fields (Jacobian), a folded field, TRE of a known field.
#include <gtest/gtest.h>

#include <cmath>
#include <nlohmann/json.hpp>

#include "box_mesh.h"
#include "core/errors.h"
#include "field/metrics.h"

namespace brainshift {
namespace {

Grid3 cube_grid(int n, double spacing_mm) {
  Grid3 g;
  g.dims = {n, n, n};
  g.world_from_voxel.topLeftCorner<3, 3>() *= spacing_mm;
  const double half = 0.5 * (n - 1) * spacing_mm;
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-half, -half, -half);
  return g;
}

Mask sphere(const Grid3& g, const Eigen::Vector3d& centre, double radius) {
  Mask m(g, 0);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) m.at(i, j, k) = (g.world_mm(i, j, k) - centre).norm() <= radius;
  return m;
}

LabelImage as_labels(const Mask& m, std::uint16_t label) {
  LabelImage l(m.grid, 0);
  for (std::size_t v = 0; v < m.voxels.size(); ++v) l.voxels[v] = m.voxels[v] ? label : 0;
  return l;
}

constexpr double kPi = 3.14159265358979323846;
constexpr double kR = 15.0, kD = 4.0;

TEST(Metrics, DiceOfOffsetSpheresMatchesAnalyticLens) {
  const Grid3 g = cube_grid(80, 0.5);
  const LabelImage a = as_labels(sphere(g, Eigen::Vector3d(-kD / 2, 0, 0), kR), 4);
  const LabelImage b = as_labels(sphere(g, Eigen::Vector3d(kD / 2, 0, 0), kR), 4);
  // Lens volume of two spheres of radius R with centres d apart.
  const double lens = kPi * (4 * kR + kD) * (2 * kR - kD) * (2 * kR - kD) / 12.0;
  const double ball = 4.0 / 3.0 * kPi * kR * kR * kR;
  const double analytic = lens / ball;
  const auto dice = dice_per_label(a, b, {4, 2});
  ASSERT_EQ(dice.size(), 2u);
  EXPECT_NEAR(dice[0].dice, analytic, 0.02 * analytic);
  EXPECT_NEAR(dice[0].volume_a_ml, ball / 1000.0, 0.02 * ball / 1000.0);
  EXPECT_DOUBLE_EQ(dice[1].dice, 1.0);  // absent from both
  EXPECT_DOUBLE_EQ(dice_per_label(a, a, {4})[0].dice, 1.0);
}

// Mean distance from a sphere's surface to the same sphere shifted by d:
// |sqrt(R^2 + d^2 - 2 R d t) - R| averaged over t = cos(theta) uniform in [-1, 1].
double analytic_mean_surface_distance() {
  const int n = 200000;
  double sum = 0;
  for (int s = 0; s < n; ++s) {
    const double t = -1.0 + 2.0 * (s + 0.5) / n;
    sum += std::abs(std::sqrt(kR * kR + kD * kD - 2 * kR * kD * t) - kR);
  }
  return sum / n;
}

TEST(Metrics, SurfaceDistancesOfOffsetSpheres) {
  const Grid3 g = cube_grid(80, 0.5);
  const Mask a = sphere(g, Eigen::Vector3d(-kD / 2, 0, 0), kR);
  const Mask b = sphere(g, Eigen::Vector3d(kD / 2, 0, 0), kR);
  const SurfaceDistance s = surface_distance(a, b);
  const double mean = analytic_mean_surface_distance();  // ~2.0 mm
  EXPECT_NEAR(s.mean_mm, mean, 0.25);
  EXPECT_NEAR(s.hausdorff_mm, kD, 0.5);  // attained at the far poles
  EXPECT_GT(s.hd95_mm, mean);
  EXPECT_LE(s.hd95_mm, s.hausdorff_mm);
  const SurfaceDistance same = surface_distance(a, a);
  EXPECT_DOUBLE_EQ(same.mean_mm, 0.0);
  EXPECT_DOUBLE_EQ(same.hausdorff_mm, 0.0);
  EXPECT_THROW(surface_distance(a, Mask(g, 0)), InputError);
  EXPECT_THROW(surface_distance(a, Mask(cube_grid(10, 0.5), 1)), InputError);
}

TEST(Metrics, JacobianOfUniformScaling) {
  // x -> 1.1 x, i.e. u(x) = 0.1 x, on an oblique anisotropic grid: det = 1.331.
  const Grid3 g = test::oblique_grid({12, 10, 8}, Eigen::Vector3d(0.9, 1.1, 2.5), Eigen::Vector3d(-5, 3, 7), 0.5);
  VectorImage3 u(g);
  for (int k = 0; k < 8; ++k)
    for (int j = 0; j < 10; ++j)
      for (int i = 0; i < 12; ++i) u.vectors[g.index(i, j, k)] = (0.1 * g.world_mm(i, j, k)).cast<float>();
  const JacobianStats s = jacobian_stats(u, nullptr);
  EXPECT_NEAR(s.min_det, 1.331, 1e-4);
  EXPECT_NEAR(s.max_det, 1.331, 1e-4);
  EXPECT_EQ(s.folded_voxels, 0u);
  EXPECT_EQ(s.voxels, g.voxel_count());
}

TEST(Metrics, FoldedFieldIsDetectedInsideMask) {
  const Grid3 g = cube_grid(20, 1.0);
  VectorImage3 u(g);
  Mask fold(g, 0);
  // x -> x - 2 x_local in a slab: the map reverses x there (det = -1).
  for (int k = 0; k < 20; ++k)
    for (int j = 0; j < 20; ++j)
      for (int i = 0; i < 20; ++i) {
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        u.vectors[g.index(i, j, k)] = Eigen::Vector3f(float(-2.0 * x.x()), 0.f, 0.f);
        fold.at(i, j, k) = (i >= 5 && i < 15);
      }
  const JacobianStats s = jacobian_stats(u, &fold);
  EXPECT_EQ(s.voxels, 10u * 20 * 20);
  EXPECT_EQ(s.folded_voxels, s.voxels);
  EXPECT_NEAR(s.min_det, -1.0, 1e-5);
  const ImageF det = jacobian_determinant(VectorImage3(g));
  for (const float d : det.voxels) ASSERT_FLOAT_EQ(d, 1.f);
}

TEST(Metrics, TargetRegistrationErrorOfKnownField) {
  const Grid3 g = cube_grid(30, 1.0);
  VectorImage3 u(g);
  std::fill(u.vectors.begin(), u.vectors.end(), Eigen::Vector3f(1, -2, 0.5));
  std::vector<Eigen::Vector3d> x, p;
  const std::vector<double> errors{0.0, 1.0, 2.0, 3.0, 10.0};
  for (std::size_t n = 0; n < errors.size(); ++n) {
    x.emplace_back(-5.0 + n, 2.3, 1.7 * n);
    p.push_back(x.back() + Eigen::Vector3d(1, -2, 0.5) + errors[n] * Eigen::Vector3d(0, 0.6, 0.8));
  }
  const TreStats s = target_registration_error(u, x, p);
  ASSERT_EQ(s.errors_mm.size(), 5u);
  for (std::size_t n = 0; n < errors.size(); ++n) EXPECT_NEAR(s.errors_mm[n], errors[n], 1e-5);
  EXPECT_NEAR(s.mean_mm, 3.2, 1e-5);
  EXPECT_NEAR(s.median_mm, 2.0, 1e-5);
  EXPECT_NEAR(s.p95_mm, 3.0 + 0.8 * 7.0, 1e-5);  // position 3.8 between 3 and 10
  EXPECT_NEAR(s.max_mm, 10.0, 1e-5);
  x.back() = Eigen::Vector3d(100, 0, 0);
  EXPECT_THROW(target_registration_error(u, x, p), InputError);
  p.pop_back();
  EXPECT_THROW(target_registration_error(u, x, p), InputError);
}

TEST(Metrics, JsonCarriesTheNumbers) {
  nlohmann::json j = SurfaceDistance{1.5, 3.5, 4.0, 10, 12};
  EXPECT_DOUBLE_EQ(j.at("hd95_mm").get<double>(), 3.5);
  j = LabelDice{2, 0.9, 20.0, 21.0};
  EXPECT_EQ(j.at("label").get<int>(), 2);
  j = JacobianStats{0.5, 1.5, 3, 100};
  EXPECT_EQ(j.at("folded_voxels").get<int>(), 3);
  TreStats t;
  t.errors_mm = {1.0, 2.0};
  t.mean_mm = 1.5;
  j = t;
  EXPECT_EQ(j.at("errors_mm").size(), 2u);
  EXPECT_DOUBLE_EQ(j.at("mean_mm").get<double>(), 1.5);
  EXPECT_NEAR(percentile({4, 1, 3, 2}, 50), 2.5, 1e-12);
}

}  // namespace
}  // namespace brainshift
