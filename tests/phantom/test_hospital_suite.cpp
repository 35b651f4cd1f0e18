// The hospital-variation suite's generator (engine/phantom/hospital_suite.h)
// must be what it claims, on the small synthetic head (seconds):
// - the subject warp and the new deformation terms are invertible (to 1e-3
//   mm) with a positive Jacobian, and do what they are named for (ventricles
//   enlarged or compressed, a dent of the stated depth);
// - the scanner grids have the requested spacing and orientation;
// - the segmentation is made by the algorithm from the image, so it differs
//   from the truth in the expected ways (T2-like larger, thick slices
//   eroded) while still a segmentation of the same brain (Dice > 0.9);
// - a case is determined by its seed.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <set>

#include "core/errors.h"
#include "image/distance_map.h"
#include "phantom/hospital_suite.h"
#include "synthetic_head.h"

namespace brainshift {
namespace {

// The synthetic head with cortical folding in its T1: sulci (CSF, 3 mm
// wide, every 12 mm along S and R) in the outer 9 mm of the brain; the
// labels keep them inside the brain, as a brain mask closed over its sulci.
const test::SyntheticHead& head() {
  static const test::SyntheticHead h = [] {
    test::SyntheticHead f = test::synthetic_head();
    const Grid3& g = f.t1.grid;
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          if (f.labels.at(i, j, k) != 1) continue;
          const Eigen::Vector3d p = g.world_mm(i, j, k);
          const double e = p.cwiseQuotient(Eigen::Vector3d(55, 65, 48)).norm();
          const bool sulcus = std::abs(std::sin(3.14159265 * p.z() / 12)) < 0.26 ||
                              std::abs(std::sin(3.14159265 * p.x() / 12)) < 0.26;
          if (e > 0.83 && sulcus) f.t1.at(i, j, k) = 30.f;
        }
    return f;
  }();
  return h;
}

Subject synthetic_subject() { return {"synthetic", head().t1, head().labels, {}}; }

std::size_t count(const LabelImage& l, std::uint16_t v) {
  return static_cast<std::size_t>(std::count(l.voxels.begin(), l.voxels.end(), v));
}

// Points on a lattice over the brain's box.
std::vector<Eigen::Vector3d> brain_points() {
  std::vector<Eigen::Vector3d> p;
  for (double x = -50; x <= 50; x += 10)
    for (double y = -60; y <= 60; y += 10)
      for (double z = -44; z <= 44; z += 11) p.emplace_back(x, y, z);
  return p;
}

template <class F>
double jacobian_det(F&& f, const Eigen::Vector3d& p) {
  const double h = 0.05;
  Eigen::Matrix3d j;
  for (int a = 0; a < 3; ++a)
    j.col(a) = (f(p + h * Eigen::Vector3d::Unit(a)) - f(p - h * Eigen::Vector3d::Unit(a))) / (2 * h);
  return j.determinant();
}

TEST(HospitalSuite, SubjectWarpIsInvertibleAndEnlargesOrCompressesTheVentricles) {
  SubjectSpec s;
  s.name = "test_hydro";
  s.seed = 3;
  s.axis_scale = {1.08, 0.93, 1.05};
  s.reshape_bumps = 4;
  s.reshape_amplitude_mm = 4;
  s.reshape_width_mm = 25;
  s.ventricle_volume_factor = 2.0;
  const SubjectWarp warp(head().labels, s);
  for (const auto& y : brain_points()) {
    EXPECT_LT((warp.forward(warp.inverse(y)) - y).norm(), 1e-3) << y.transpose();
    EXPECT_LT((warp.inverse(warp.forward(y)) - y).norm(), 1e-3) << y.transpose();
    EXPECT_GT(jacobian_det([&](const Eigen::Vector3d& p) { return warp.forward(p); }, y), 0.0) << y.transpose();
  }
  const Subject subject = make_subject(head().t1, head().labels, s);
  const double factor = static_cast<double>(count(subject.labels, 2)) / count(head().labels, 2);
  EXPECT_GT(factor, 1.6) << subject.description.dump();
  EXPECT_LT(factor, 2.4) << subject.description.dump();
  // The brain follows the scale (1.08 x 0.93 x 1.05 = 1.05) and the ventricles' growth.
  EXPECT_GT(count(subject.labels, 1) + count(subject.labels, 2), count(head().labels, 1) + count(head().labels, 2));

  SubjectSpec m;
  m.name = "test_mass";
  m.mass_effect = MassEffectSpec{};
  m.mass_effect->radius_mm = 7;
  m.mass_effect->push_mm = 5;
  m.mass_effect->gap_mm = 6;
  const SubjectWarp push(head().labels, m);
  for (const auto& y : brain_points()) {
    EXPECT_LT((push.forward(push.inverse(y)) - y).norm(), 1e-3) << y.transpose();
    EXPECT_GT(jacobian_det([&](const Eigen::Vector3d& p) { return push.forward(p); }, y), 0.0) << y.transpose();
  }
  const Subject compressed = make_subject(head().t1, head().labels, m);
  EXPECT_LT(count(compressed.labels, 2), 0.97 * count(head().labels, 2)) << compressed.description.dump();
  EXPECT_GT(count(compressed.labels, 4), count(head().labels, 4)) << "the mass-effect tumour is implanted";

  m.tumor = TumorImplantSpec{};
  EXPECT_THROW(SubjectWarp(head().labels, m), InputError);
}

TEST(HospitalSuite, NewDeformationsAreInvertibleWithTheStatedDent) {
  PhantomSpec p;
  p.name = "test_deformation";
  p.sinking.cortex_mm = 22;
  p.sinking.deep_mm = 4;
  p.sinking.depth_decay_mm = 35;
  p.midline_shift.enabled = true;
  p.midline_shift.amplitude_mm = 5;
  p.resection.enabled = true;  // the synthetic head's tumour, half of it
  p.resection.resected_fraction = 0.5;
  p.resection.collapse_mm = 2;
  PhantomSpec dented = p;
  dented.retractor.enabled = true;
  dented.retractor.depth_mm = 7;
  dented.retractor.half_width_mm = 2.5;
  const PhantomDeformation without(head().labels, p), with(head().labels, dented);
  for (const auto& y : brain_points()) {
    EXPECT_LT((with.forward(with.inverse(y)) - y).norm(), 1e-3) << y.transpose();
    EXPECT_LT((with.inverse(with.forward(y)) - y).norm(), 1e-3) << y.transpose();
    EXPECT_GT(jacobian_det([&](const Eigen::Vector3d& q) { return with.forward(q); }, y), 0.0) << y.transpose();
  }
  // Under the blade, at the sunken surface, the dent moves the tissue by its depth.
  const Eigen::Vector3d under = with.craniotomy_mm() + 0.5 * (-p.sinking.craniotomy_direction.normalized());
  EXPECT_NEAR((with.forward(under) - without.forward(under)).norm(), 7.0, 1.0);
  // 8 mm beside the blade, across it: much less (a steep dent, not a sink).
  const Eigen::Vector3d across = p.sinking.craniotomy_direction.normalized().cross(Eigen::Vector3d::UnitX()).normalized();
  EXPECT_LT((with.forward(under + 8 * across) - without.forward(under + 8 * across)).norm(), 3.0);
  // The grid Jacobian of the whole case stays positive (the scale-down rule).
  const PhantomCase c = make_phantom(head().t1, head().labels, [&] {
    PhantomSpec s = dented;
    s.dims = {60, 70, 40};
    s.spacing_mm = {2, 2, 3};
    s.landmark_count = 30;
    return s;
  }());
  EXPECT_GT(c.description["min_jacobian"].get<double>(), 0.0);
}

ScannerSpec small_scanner(const Eigen::Vector3d& spacing, Contrast contrast) {
  ScannerSpec s;
  s.name = "test";
  s.spacing_mm = spacing;
  s.fov_mm = {135, 150, 120};
  s.snr = 25;
  s.bias_amplitude = 0.1;
  s.contrast = contrast;
  return s;
}

HospitalCaseSpec small_case(const ScannerSpec& scanner) {
  HospitalCaseSpec c;
  c.subject = "synthetic";
  c.deformation.name = "test_case";
  c.deformation.seed = 9;
  c.deformation.sinking.cortex_mm = 8;
  c.deformation.landmark_count = 40;
  c.scanner = scanner;
  return c;
}

TEST(HospitalSuite, ScannerGridsHaveTheRequestedSpacingAndOrientation) {
  ScannerSpec sagittal = small_scanner({1.5, 1.5, 3}, Contrast::t1);
  sagittal.orientation_deg = sagittal_deg();
  const HospitalCase s = make_hospital_case(synthetic_subject(), small_case(sagittal));
  const Grid3& g = s.phantom.intraop_t1.grid;
  EXPECT_TRUE(g.same_geometry(s.phantom.intraop_labels.grid));
  EXPECT_TRUE(g.same_geometry(s.phantom.true_pullback_mm.grid));
  EXPECT_NEAR((g.spacing_mm() - Eigen::Vector3d(1.5, 1.5, 3)).norm(), 0.0, 1e-9);
  const Eigen::Vector3d slice_axis = g.world_from_voxel.block<3, 1>(0, 2).normalized();
  EXPECT_GT(std::abs(slice_axis.x()), 0.999) << "sagittal slices are stacked along R";

  ScannerSpec tilted = small_scanner({2, 2, 3}, Contrast::t1);
  tilted.orientation_deg = {28, 0, 0};
  const HospitalCase t = make_hospital_case(synthetic_subject(), small_case(tilted));
  const Eigen::Vector3d normal = t.phantom.intraop_t1.grid.world_from_voxel.block<3, 1>(0, 2).normalized();
  EXPECT_NEAR(std::acos(normal.z()) * 180 / 3.14159265358979, 28.0, 1e-6);
}

TEST(HospitalSuite, AFieldOfViewMovedUpCutsTheBase) {
  const ScannerSpec centred = small_scanner({2, 2, 3}, Contrast::t1);
  ScannerSpec raised = centred;
  raised.fov_centre_offset_mm = {0, 0, 40};
  const HospitalCase c = make_hospital_case(synthetic_subject(), small_case(centred));
  const HospitalCase r = make_hospital_case(synthetic_subject(), small_case(raised));
  const Grid3& gc = c.phantom.intraop_t1.grid;
  const Grid3& gr = r.phantom.intraop_t1.grid;
  EXPECT_EQ(gc.dims, gr.dims);
  EXPECT_NEAR((gr.world_mm(0, 0, 0) - gc.world_mm(0, 0, 0) - Eigen::Vector3d(0, 0, 40)).norm(), 0.0, 1e-9);
  // Less of the brain in view, none of it lost from the truth's labels in view.
  const auto brain = [](const LabelImage& l) { return std::count_if(l.voxels.begin(), l.voxels.end(), [](auto v) { return v != 0; }); };
  EXPECT_LT(brain(r.true_labels), brain(c.true_labels));
  ScannerSpec far = centred;
  far.fov_centre_offset_mm = {0, 0, 500};
  EXPECT_THROW(make_hospital_case(synthetic_subject(), small_case(far)), InputError);
}

TEST(HospitalSuite, AlgorithmicSegmentationErrsAsItsImageMakesIt) {
  auto brain_ratio = [](const HospitalCase& c) {
    return c.description["segmentation"]["against_truth"]["brain_volume_ratio"].get<double>();
  };
  auto brain_dice = [](const HospitalCase& c) {
    return c.description["segmentation"]["against_truth"]["brain_dice"].get<double>();
  };
  const HospitalCase iso = make_hospital_case(synthetic_subject(), small_case(small_scanner({1.5, 1.5, 1.5}, Contrast::t1)));
  const HospitalCase thick = make_hospital_case(synthetic_subject(), small_case(small_scanner({1.5, 1.5, 4.5}, Contrast::t1)));
  const HospitalCase t2 = make_hospital_case(synthetic_subject(), small_case(small_scanner({1.5, 1.5, 1.5}, Contrast::t2_like)));
  for (const HospitalCase* c : {&iso, &thick, &t2}) {
    EXPECT_GT(brain_dice(*c), 0.9) << c->description["segmentation"].dump();
    EXPECT_GT(c->description["segmentation"]["ventricle_seeds"]["found"].get<int>(), 0);
    EXPECT_GT(count(c->phantom.intraop_labels, 2), 0u);
  }
  // The labels are not the truth: the algorithm met the image.
  EXPECT_LT(brain_dice(iso), 0.999);
  EXPECT_LT(brain_ratio(iso), 1.0) << "sulci open at the surface are left out";
  EXPECT_LT(brain_ratio(thick), brain_ratio(iso) - 0.005) << "thick slices erode the mask (partial volume)";
  // Bright CSF: the T2-like image's own errors (other thresholds, other
  // partial-volume voxels), not the T1's.
  EXPECT_NE(brain_ratio(t2), brain_ratio(iso));
  EXPECT_LT(label_dice(t2.phantom.intraop_labels, iso.phantom.intraop_labels, 1), 0.99);
}

// Gadolinium: a bright shell (the enhancing dura) hugs the brain; inside the
// brain, away from any cavity, the image is the T1's, voxel for voxel (the
// same seed draws the same noise).
TEST(HospitalSuite, AContrastEnhancedT1BrightensAShellRoundTheBrainOnly) {
  const HospitalCase t1 = make_hospital_case(synthetic_subject(), small_case(small_scanner({1.5, 1.5, 1.5}, Contrast::t1)));
  const HospitalCase gd = make_hospital_case(
      synthetic_subject(), small_case(small_scanner({1.5, 1.5, 1.5}, Contrast::t1_contrast_enhanced)));
  const Grid3& g = t1.true_labels.grid;
  Mask brain(g, 0), outside(g, 0);
  for (std::size_t v = 0; v < brain.voxels.size(); ++v) {
    brain.voxels[v] = t1.true_labels.voxels[v] != 0;
    outside.voxels[v] = !brain.voxels[v];
  }
  const ImageF out_mm = distance_to_mask_mm(brain), in_mm = distance_to_mask_mm(outside);
  std::vector<float> brain_values;
  for (std::size_t v = 0; v < brain.voxels.size(); ++v)
    if (brain.voxels[v]) brain_values.push_back(t1.phantom.intraop_t1.voxels[v]);
  std::nth_element(brain_values.begin(), brain_values.begin() + brain_values.size() / 2, brain_values.end());
  const double brain_median = brain_values[brain_values.size() / 2];
  double shell_gain = 0;
  std::size_t shell = 0, deep = 0, deep_changed = 0;
  for (std::size_t v = 0; v < brain.voxels.size(); ++v) {
    const double d = gd.phantom.intraop_t1.voxels[v] - t1.phantom.intraop_t1.voxels[v];
    if (out_mm.voxels[v] > 0 && out_mm.voxels[v] <= 6.0) {
      shell_gain += d;
      ++shell;
    }
    if (in_mm.voxels[v] > 4.0) {
      ++deep;
      deep_changed += d != 0;
    }
  }
  ASSERT_GT(shell, 0u);
  ASSERT_GT(deep, 0u);
  EXPECT_GT(shell_gain / shell, 0.1 * brain_median) << "no enhancing shell round the brain";
  EXPECT_LT(static_cast<double>(deep_changed) / deep, 0.02) << "the brain itself changed";
  EXPECT_EQ(gd.description["scanner"].value("contrast", ""), "t1_contrast_enhanced") << gd.description.dump();
  EXPECT_GT(count(gd.phantom.intraop_labels, 2), 0u) << "the segmenter found no ventricles on the enhanced T1";
}

// FLAIR-like, on a scene of one voxel per tissue (scene_contrast, before
// the scanner's blur, bias and noise): the fluid nulled as on a T1, grey
// matter brighter than white as on a T2, blood bright, fat stays bright.
TEST(HospitalSuite, AFlairLikeImageDarkensTheFluidAndPutsGreyOverWhite) {
  Grid3 g;
  g.dims = {7, 1, 1};
  IntraopScene scene;
  scene.t1 = ImageF(g, 0.f);
  scene.classes = Image3<std::uint8_t>(g, 0);
  scene.csf_t1 = 30, scene.gm_t1 = 80, scene.wm_t1 = 110, scene.brain_median_t1 = 100;
  const std::pair<SceneClass, float> voxels[7] = {
      {SceneClass::tissue, 30},  {SceneClass::tissue, 86},  {SceneClass::tissue, 110},
      {SceneClass::extracerebral_csf, 30}, {SceneClass::cavity_fluid, 30}, {SceneClass::blood, 60},
      {SceneClass::head, 160}};
  for (int i = 0; i < 7; ++i) {
    scene.classes.voxels[i] = static_cast<std::uint8_t>(voxels[i].first);
    scene.t1.voxels[i] = voxels[i].second;
  }
  const ImageF t1 = scene_contrast(scene, Contrast::t1), flair = scene_contrast(scene, Contrast::flair_like);
  const auto& f = flair.voxels;
  EXPECT_LT(t1.voxels[1], t1.voxels[2]) << "T1: grey darker than white";
  EXPECT_GT(f[1], f[2]) << "FLAIR: grey brighter than white";
  EXPECT_LT(f[0], 0.3 * f[2]) << "FLAIR: fluid in the brain's tissue nulled";
  EXPECT_LT(f[3], 0.3 * f[2]) << "FLAIR: the subarachnoid CSF nulled";
  EXPECT_LT(f[4], 0.3 * f[2]) << "FLAIR: the cavity's fluid nulled";
  EXPECT_GT(f[5], f[2]) << "FLAIR: blood bright";
  EXPECT_GT(f[6], f[1]) << "FLAIR: the scalp's fat bright";
}

// The suite's FLAIR-like case names its contrast.
TEST(HospitalSuite, AFlairLikeCaseSaysItsContrast) {
  const HospitalCase flair =
      make_hospital_case(synthetic_subject(), small_case(small_scanner({2, 2, 3}, Contrast::flair_like)));
  EXPECT_EQ(flair.description["scanner"].value("contrast", ""), "flair_like") << flair.description.dump();
  EXPECT_GT(count(flair.phantom.intraop_labels, 1), 0u) << "the threshold segmenter found no brain";
}

TEST(HospitalSuite, DeterministicFromTheSeed) {
  const HospitalCaseSpec spec = small_case(small_scanner({2, 2, 3}, Contrast::t1));
  const HospitalCase a = make_hospital_case(synthetic_subject(), spec);
  const HospitalCase b = make_hospital_case(synthetic_subject(), spec);
  EXPECT_EQ(a.phantom.intraop_t1.voxels, b.phantom.intraop_t1.voxels);
  EXPECT_EQ(a.phantom.intraop_labels.voxels, b.phantom.intraop_labels.voxels);
  EXPECT_EQ(a.phantom.landmarks_intraop_preop_mm, b.phantom.landmarks_intraop_preop_mm);
  HospitalCaseSpec other = spec;
  other.deformation.seed = 10;
  const HospitalCase c = make_hospital_case(synthetic_subject(), other);
  EXPECT_NE(a.phantom.intraop_t1.voxels, c.phantom.intraop_t1.voxels);
}

TEST(HospitalSuite, SuiteNamesItsPartsAndRejectsBadSpecs) {
  const auto suite = hospital_suite();
  EXPECT_GE(suite.size(), 8u);
  EXPECT_LE(suite.size(), 16u);
  std::set<std::string> subjects;
  for (const auto& s : hospital_subjects()) subjects.insert(s.name);
  for (const auto& c : suite) EXPECT_TRUE(subjects.count(c.subject)) << c.deformation.name;
  SubjectSpec bad;
  bad.axis_scale = {1.5, 1, 1};
  EXPECT_THROW(make_subject(head().t1, head().labels, bad), InputError);
  PhantomSpec steep;
  steep.retractor.enabled = true;
  steep.retractor.depth_mm = 15;
  steep.retractor.depth_decay_mm = 5;
  EXPECT_THROW(PhantomDeformation(head().labels, steep), InputError);
}

}  // namespace
}  // namespace brainshift
