// The plausibility gates one by one, on inputs whose answer is known: a gate
// must trip on what is impossible for one patient and pass what brain shift
// and head positioning allow.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "box_mesh.h"  // tests/fem
#include "quality/left_right_check.h"
#include "quality/plausibility_gates.h"

using namespace brainshift;

namespace {

Eigen::Matrix4d linear(const Eigen::Matrix3d& L) {
  Eigen::Matrix4d A = Eigen::Matrix4d::Identity();
  A.topLeftCorner<3, 3>() = L;
  return A;
}

Eigen::Matrix4d rotation_deg(double deg, const Eigen::Vector3d& axis) {
  return linear(Eigen::AngleAxisd(deg * M_PI / 180.0, axis.normalized()).toRotationMatrix());
}

Grid3 cube_grid(int n, double spacing_mm) {
  Grid3 g;
  g.dims = {n, n, n};
  g.world_from_voxel.topLeftCorner<3, 3>() *= spacing_mm;
  g.world_from_voxel.block<3, 1>(0, 3) = Eigen::Vector3d::Constant(-0.5 * (n - 1) * spacing_mm);
  return g;
}

// A "brain" ball (1) with a ventricle (2) left of the midline only and a
// tumour (4) right, frontal: every structure but the ball is asymmetric.
LabelImage asymmetric_head() {
  LabelImage l(cube_grid(64, 1.5));
  for (int k = 0; k < 64; ++k)
    for (int j = 0; j < 64; ++j)
      for (int i = 0; i < 64; ++i) {
        const Eigen::Vector3d p = l.grid.world_mm(i, j, k);
        std::uint16_t v = 0;
        if (p.norm() < 40) v = 1;
        if ((p - Eigen::Vector3d(-10, 0, 5)).cwiseQuotient(Eigen::Vector3d(6, 18, 8)).norm() < 1) v = 2;
        if ((p - Eigen::Vector3d(18, 15, -5)).norm() < 7) v = 4;
        l.at(i, j, k) = v;
      }
  return l;
}

LabelImage mirrored(const LabelImage& in) {
  LabelImage out = in;
  const auto& d = in.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) out.at(i, j, k) = in.at(d[0] - 1 - i, j, k);
  return out;
}

const std::vector<std::pair<std::string, std::uint16_t>> kAsymmetric{{"ventricles", 2}, {"tumor", 4}};

}  // namespace

TEST(VolumeGate, AFewPerCentPassesALeakOfTensOfPerCentFails) {
  const PlausibilityLimits limits;
  EXPECT_TRUE(volume_gate(1040, 1000, Eigen::Matrix4d::Identity(), limits).passed);
  EXPECT_TRUE(volume_gate(960, 1000, Eigen::Matrix4d::Identity(), limits).passed);
  const GateResult leak = volume_gate(1300, 1000, Eigen::Matrix4d::Identity(), limits);
  EXPECT_FALSE(leak.passed);
  EXPECT_NEAR(leak.value, 0.30, 1e-9);
  EXPECT_FALSE(volume_gate(700, 1000, Eigen::Matrix4d::Identity(), limits).passed) << "a lost lobe";
  // The preop is mapped by the affine: a scaled affine scales its volume.
  EXPECT_NEAR(volume_gate(1331, 1000, linear(Eigen::Matrix3d::Identity() * 1.1), limits).value, 0.0, 1e-9);
}

TEST(VolumeGate, FluidWhereTheBrainWasCountsWithTheBrain) {
  const PlausibilityLimits limits;
  // A 20 % gap under the dura, found as fluid: the skull still holds the volume.
  EXPECT_FALSE(volume_gate(800, 1000, Eigen::Matrix4d::Identity(), limits).passed);
  const GateResult sunk = volume_gate(800, 1000, Eigen::Matrix4d::Identity(), limits, 180);
  EXPECT_TRUE(sunk.passed);
  EXPECT_NEAR(sunk.value, 0.02, 1e-9);
  // Fluid does not excuse a leak.
  EXPECT_FALSE(volume_gate(1300, 1000, Eigen::Matrix4d::Identity(), limits, 50).passed);
}

TEST(VolumeGate, OnlyThePreopInsideTheFieldOfViewIsCompared) {
  // A 64-voxel cube of brain; the intraop grid holds its upper 48 slices.
  LabelImage preop(cube_grid(64, 1.5));
  for (int k = 8; k < 56; ++k)
    for (int j = 8; j < 56; ++j)
      for (int i = 8; i < 56; ++i) preop.at(i, j, k) = 1;
  EXPECT_NEAR(preop_in_view(preop, preop.grid, Eigen::Matrix4d::Identity()).fraction, 1.0, 1e-12);
  Grid3 slab = preop.grid;
  slab.dims[2] = 32;  // slices 0..31 only: brain slices 8..31 of 8..55
  const double in_view = preop_in_view(preop, slab, Eigen::Matrix4d::Identity()).fraction;
  EXPECT_NEAR(in_view, 0.5, 0.03);
  // The same slab seen after the head moved up by 12 mm (8 voxels): less brain in view.
  Eigen::Matrix4d up = Eigen::Matrix4d::Identity();
  up(2, 3) = 12.0;
  EXPECT_NEAR(preop_in_view(preop, slab, up).fraction, 16.0 / 48.0, 0.03);
  // Nothing in view at all (the grid far away).
  Eigen::Matrix4d away = Eigen::Matrix4d::Identity();
  away(0, 3) = 500.0;
  EXPECT_EQ(preop_in_view(preop, slab, away).fraction, 0.0);
}

TEST(VolumeGate, VentriclesMayShrinkButNotCoverTheBrain) {
  const PlausibilityLimits limits;
  EXPECT_TRUE(ventricle_volume_gate(10, 25, Eigen::Matrix4d::Identity(), limits).passed) << "drained CSF";
  EXPECT_FALSE(ventricle_volume_gate(900, 25, Eigen::Matrix4d::Identity(), limits).passed) << "labels swapped";
  EXPECT_FALSE(ventricle_volume_gate(0, 25, Eigen::Matrix4d::Identity(), limits).tested);
}

TEST(AffineGates, AHeadMovingPassesScaleShearAndFlipsFail) {
  const PlausibilityLimits limits;
  // A whole adult brain in view: about 130 mm along every direction.
  const auto whole_brain = [](const Eigen::Vector3d&) { return 130.0; };
  const auto passes = [&](const Eigen::Matrix4d& A) {
    const auto g = affine_gates(A, limits, whole_brain);
    return g[0].passed && g[1].passed;
  };
  EXPECT_TRUE(passes(Eigen::Matrix4d::Identity()));
  EXPECT_TRUE(passes(rotation_deg(40, {1, 0.3, 0.2}) * linear(Eigen::Vector3d(1.03, 0.98, 1.01).asDiagonal())));
  EXPECT_TRUE(passes(linear(Eigen::Vector3d(1.0, 1.0, 1.1).asDiagonal()))) << "an affine dragged by a deep sink";
  EXPECT_FALSE(passes(linear(Eigen::Vector3d(1.0, 1.0, 1.2).asDiagonal()))) << "scale";
  EXPECT_FALSE(passes(linear(Eigen::Vector3d(0.8, 1.0, 1.0).asDiagonal()))) << "shrink";
  Eigen::Matrix3d shear = Eigen::Matrix3d::Identity();
  shear(0, 1) = 0.4;
  EXPECT_FALSE(passes(linear(shear))) << "shear";
  EXPECT_FALSE(passes(linear(Eigen::Vector3d(-1, 1, 1).asDiagonal()))) << "mirror";
  const auto turned = affine_gates(rotation_deg(120, {0, 0, 1}), limits, whole_brain);
  EXPECT_TRUE(turned[0].passed);
  EXPECT_FALSE(turned[1].passed);
  EXPECT_NEAR(turned[1].value, 120.0, 1e-6);
}

TEST(AffineGates, AShortViewAllowsASinkItsShareOnlyAlongTheShortDirection) {
  const PlausibilityLimits limits;
  // 85 mm of brain seen head-foot (a short coil), 130 mm across.
  const auto short_coil = [](const Eigen::Vector3d& v) { return std::abs(v.z()) > 0.9 ? 85.0 : 130.0; };
  const auto whole_brain = [](const Eigen::Vector3d&) { return 130.0; };
  // A 22 mm vertex sinking seen through it compresses the label affine by 13 % along gravity.
  const Eigen::Matrix4d sink = linear(Eigen::Vector3d(1.01, 1.01, 0.866).asDiagonal());
  const auto seen_short = affine_gates(sink, limits, short_coil);
  EXPECT_TRUE(seen_short[0].passed) << seen_short[0].value << " " << seen_short[0].limit;
  EXPECT_NEAR(seen_short[0].value, 1.0 / 0.866 - 1.0, 1e-9);
  EXPECT_NEAR(seen_short[0].extra["directions"][2]["brain_extent_in_view_mm"].get<double>(), 85.0, 1e-9);
  // 0.85 along gravity (deviation 0.176, under the 0.221 an 85 mm view allows)
  // passes there, but not across the head nor with the whole brain in view
  // (limit 0.155): there it is another head.
  const Eigen::Matrix4d deeper = linear(Eigen::Vector3d(1.0, 1.0, 0.85).asDiagonal());
  EXPECT_TRUE(affine_gates(deeper, limits, short_coil)[0].passed);
  EXPECT_FALSE(affine_gates(deeper, limits, whole_brain)[0].passed);
  const Eigen::Matrix4d across = linear(Eigen::Vector3d(0.85, 1.0, 1.0).asDiagonal());
  EXPECT_FALSE(affine_gates(across, limits, short_coil)[0].passed);
  // The limit falls with the extent seen and never below the scanner's and segmentation's own error.
  EXPECT_GT(affine_stretch_limit(60, limits), affine_stretch_limit(130, limits));
  EXPECT_LT(affine_stretch_limit(0, limits), 0.4) << "no brain in view licenses no stretch";
  EXPECT_GT(affine_stretch_limit(1e6, limits), limits.affine_stretch_base);
  EXPECT_LT(affine_stretch_limit(1e6, limits), limits.affine_stretch_base + 1e-3);
}

TEST(AffineGates, ASinkTheImageShowsMayTakeTheDeepestSinkInFullAlongOneDirectionOnly) {
  const PlausibilityLimits limits;
  const auto short_coil = [](const Eigen::Vector3d& v) { return std::abs(v.z()) > 0.9 ? 105.0 : 140.0; };
  // A 22 mm vertex sinking through a 120 mm head-foot view, contrast-enhanced:
  // the label affine compressed the brain by 17 % along gravity (stretch
  // 0.833, deviation 0.20), over the 0.186 a 105 mm view allows a sink
  // inferred from the labels alone.
  const Eigen::Matrix4d sink = linear(Eigen::Vector3d(1.015, 1.01, 0.833).asDiagonal());
  const auto inferred = affine_gates(sink, limits, short_coil);
  EXPECT_FALSE(inferred[0].passed) << inferred[0].value << " " << inferred[0].limit;
  // With the gap under the dura found in the image, the compressed direction
  // is held to the deepest sink in full: 0.03 + 25 / 105 = 0.268.
  const auto shown = affine_gates(sink, limits, short_coil, 139.0);
  EXPECT_TRUE(shown[0].passed) << shown[0].value << " " << shown[0].limit;
  EXPECT_NEAR(shown[0].extra["directions"][2]["limit"].get<double>(), affine_sink_limit(105.0, limits), 1e-12);
  EXPECT_NEAR(affine_sink_limit(105.0, limits), 0.03 + 25.0 / 105.0, 1e-12);
  EXPECT_TRUE(shown[0].extra["directions"][2]["sink_shown"].get<bool>());
  EXPECT_FALSE(shown[0].extra["directions"][0]["sink_shown"].get<bool>());
  // Deeper than any sink: refused even when shown.
  const Eigen::Matrix4d beyond = linear(Eigen::Vector3d(1.0, 1.0, 0.75).asDiagonal());
  EXPECT_FALSE(affine_gates(beyond, limits, short_coil, 139.0)[0].passed);
  // Only the most compressed direction: a head 17 % smaller in two
  // directions (another head) is refused along the second.
  const Eigen::Matrix4d two = linear(Eigen::Vector3d(1.0, 0.85, 0.833).asDiagonal());
  EXPECT_FALSE(affine_gates(two, limits, short_coil, 139.0)[0].passed);
  // A leak inflates: a stretch above 1 never takes the sink's limit.
  const Eigen::Matrix4d leak = linear(Eigen::Vector3d(1.0, 1.0, 1.2).asDiagonal());
  EXPECT_FALSE(affine_gates(leak, limits, short_coil, 139.0)[0].passed);
}

TEST(VolumeGate, TheBrainsExtentInViewIsMeasuredAlongAnyDirection) {
  LabelImage preop(cube_grid(64, 1.5));
  for (int k = 8; k < 56; ++k)
    for (int j = 8; j < 56; ++j)
      for (int i = 8; i < 56; ++i) preop.at(i, j, k) = 1;
  const PreopInView whole = preop_in_view(preop, preop.grid, Eigen::Matrix4d::Identity());
  EXPECT_NEAR(whole.extent_mm({0, 0, 1}), 48 * 1.5, 3.0);
  // Along the diagonal the corners are thin: the percentiles trim them.
  EXPECT_GT(whole.extent_mm({1, 1, 0}), 48 * 1.5 + 10.0);
  EXPECT_LE(whole.extent_mm({1, 1, 0}), 48 * 1.5 * std::sqrt(2.0));
  Grid3 slab = preop.grid;
  slab.dims[2] = 32;  // brain slices 8..31 of 8..55
  const PreopInView cut = preop_in_view(preop, slab, Eigen::Matrix4d::Identity());
  EXPECT_NEAR(cut.extent_mm({0, 0, 1}), 24 * 1.5, 3.0);
  EXPECT_NEAR(cut.extent_mm({1, 0, 0}), 48 * 1.5, 3.0) << "across the slab, the whole cube";
}

TEST(FieldGates, RmsStrainOfAUniformStretchIsItsStrain) {
  const test::BoxMesh box = test::make_box_mesh({6, 6, 6}, {0, 0, 0}, {60, 60, 60});
  const auto stretch = [&](double e) {
    std::vector<Eigen::Vector3d> w;
    for (const auto& p : box.mesh.nodes_mm) w.emplace_back(e * (p.x() - 30), 0, 0);
    return field_gates(box.mesh, w, PlausibilityLimits{});
  };
  const auto small = stretch(0.05);
  EXPECT_NEAR(small[1].value, 0.05, 1e-9);
  EXPECT_TRUE(small[0].passed && small[1].passed);
  const auto large = stretch(0.3);
  EXPECT_FALSE(large[1].passed) << "RMS strain 0.3 over the whole brain";
  // A rigid translation has no strain at all.
  std::vector<Eigen::Vector3d> shift(box.mesh.node_count(), Eigen::Vector3d(3, -2, 1));
  EXPECT_NEAR(field_gates(box.mesh, shift, PlausibilityLimits{})[1].value, 0.0, 1e-12);
}

TEST(FieldGates, MoreThanAnyBrainShiftFails) {
  const test::BoxMesh box = test::make_box_mesh({6, 6, 6}, {0, 0, 0}, {60, 60, 60});
  std::vector<Eigen::Vector3d> w(box.mesh.node_count(), Eigen::Vector3d(0, 0, 25));
  EXPECT_TRUE(field_gates(box.mesh, w, PlausibilityLimits{})[0].passed) << "25 mm";
  w.assign(box.mesh.node_count(), Eigen::Vector3d(0, 0, 45));
  EXPECT_FALSE(field_gates(box.mesh, w, PlausibilityLimits{})[0].passed) << "45 mm";
}

TEST(LeftRightGate, TheScanAsGivenPassesItsMirrorImageFails) {
  const LabelImage preop = asymmetric_head();
  const PlausibilityLimits limits;
  const Eigen::Matrix4d A = rotation_deg(10, {0, 0, 1});
  const LabelImage intraop = [&] {
    LabelImage l(preop.grid);
    const Eigen::Matrix4d back = A.inverse();
    for (int k = 0; k < 64; ++k)
      for (int j = 0; j < 64; ++j)
        for (int i = 0; i < 64; ++i) {
          const Eigen::Vector3d p = (back * preop.grid.world_mm(i, j, k).homogeneous()).head<3>();
          const Eigen::Vector3d v = (preop.grid.voxel_from_world() * p.homogeneous()).head<3>();
          const Eigen::Vector3i r = v.array().round().cast<int>();
          if (preop.grid.contains(r.x(), r.y(), r.z())) l.at(i, j, k) = preop.at(r.x(), r.y(), r.z());
        }
    return l;
  }();
  const GateResult given = left_right_gate({preop, intraop, A, kAsymmetric}, limits);
  EXPECT_TRUE(given.passed) << given.detail;
  EXPECT_LT(given.value, 0) << "both structures should prefer the scan as given";
  const GateResult flipped = left_right_gate({preop, mirrored(intraop), A, kAsymmetric}, limits);
  EXPECT_FALSE(flipped.passed) << flipped.extra.dump();
  // With no asymmetric structure the test cannot decide and must not refuse.
  const GateResult blind = left_right_gate({preop, mirrored(intraop), A, {}}, limits);
  EXPECT_TRUE(blind.passed);
  EXPECT_EQ(blind.value, 0);

  // The preop's side made once (the warm state's) decides the same; made for
  // other structures it is not used.
  const LeftRightPreop made = left_right_preop(preop, kAsymmetric);
  LeftRightInput with_made{preop, mirrored(intraop), A, kAsymmetric};
  with_made.preop_side = &made;
  EXPECT_EQ(left_right_gate(with_made, limits).extra.dump(), flipped.extra.dump());
  const LeftRightPreop other = left_right_preop(preop, {kAsymmetric.front()});
  with_made.preop_side = &other;
  EXPECT_EQ(left_right_gate(with_made, limits).extra.dump(), flipped.extra.dump());
  EXPECT_FALSE(left_right_gate(with_made, limits).passed);
}

TEST(ImageGate, AFieldThatScramblesTheImageFailsTheIdentityPasses) {
  ImageF t1(cube_grid(40, 2.0));
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  // A smooth texture: sums of a few sines, so a displaced sample differs.
  for (int k = 0; k < 40; ++k)
    for (int j = 0; j < 40; ++j)
      for (int i = 0; i < 40; ++i) t1.at(i, j, k) = 100 + 30 * std::sin(0.5 * i) * std::cos(0.4 * j) + 20 * std::sin(0.3 * k);
  Mask brain(t1.grid, 0);
  for (int k = 5; k < 35; ++k)
    for (int j = 5; j < 35; ++j)
      for (int i = 5; i < 35; ++i) brain.at(i, j, k) = 1;
  VectorImage3 field(t1.grid);
  const GateResult same = image_gate(t1, t1, brain, field, Eigen::Matrix4d::Identity(), PlausibilityLimits{});
  EXPECT_TRUE(same.passed);
  EXPECT_NEAR(same.value, 0.0, 1e-9);
  for (auto& v : field.vectors) v = Eigen::Vector3f(6 * u(rng) - 3, 6 * u(rng) - 3, 6 * u(rng) - 3);
  const GateResult scrambled = image_gate(t1, t1, brain, field, Eigen::Matrix4d::Identity(), PlausibilityLimits{});
  EXPECT_FALSE(scrambled.passed) << scrambled.extra.dump();
}

TEST(PlausibilityReport, NamesTheFirstFailedGateAndListsEveryGate) {
  PlausibilityReport report;
  report.add(volume_gate(1000, 1000, Eigen::Matrix4d::Identity(), PlausibilityLimits{}));
  report.add(volume_gate(1500, 1000, Eigen::Matrix4d::Identity(), PlausibilityLimits{}));
  EXPECT_NE(report.first_failure().find("plausibility gate volume"), std::string::npos);
  const auto j = report.to_json();
  EXPECT_EQ(j["all_passed"], false);
  EXPECT_TRUE(j["volume"].contains("limit"));
}
