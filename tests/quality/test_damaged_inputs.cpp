// The damaged-input suite: segmentations and images broken the ways a
// conversion or a segmenter breaks them, registered end to end on the small
// synthetic head (coarse mesh) with a known deformation. Not one may come
// back as a silent "nonrigid" worse than the affine alone: each is refused
// (the marked affine-only fallback with its reason, or an input error) or
// its non-rigid result is no worse than the affine. The undamaged scan must
// pass every gate (a false refusal is a failure too).
#include <gtest/gtest.h>
#include <mpi.h>

#include <cstdio>
#include <functional>

#include "coarse_parameters.h"  // tests/support
#include "config_file.h"
#include "core/errors.h"
#include "image/resample.h"
#include "phantom/brain_shift_phantom.h"
#include "phantom_evaluation.h"  // tests/pipeline
#include "pipeline/engine_session.h"
#include "pipeline/scan_report.h"  // result_caution
#include "quality/uncertainty_map.h"
#include "synthetic_head.h"  // tests/support

using namespace brainshift;

namespace {

// The synthetic head with one more occipital horn on the left: real
// ventricles are rarely symmetric, and a mirror is only visible through
// what is not.
PreopInput asymmetric_head() {
  test::SyntheticHead h = test::synthetic_head();
  const Grid3& g = h.labels.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d p = g.world_mm(i, j, k);
        if ((p - Eigen::Vector3d(-14, -24, 4)).cwiseQuotient(Eigen::Vector3d(5, 12, 6)).norm() < 1) {
          h.labels.at(i, j, k) = 2;
          h.t1.at(i, j, k) = 30.f;
        }
      }
  return {std::move(h.t1), std::move(h.labels)};
}

using test::coarse_parameters;  // tests/support

PhantomSpec spec() {
  PhantomSpec s;
  s.name = "damaged-suite base";
  s.seed = 7;
  s.sinking.cortex_mm = 9;
  s.sinking.deep_mm = 1.5;
  s.rigid.rotation_deg = {3, -2, 4};
  s.rigid.translation_mm = {2, -1, 1.5};
  s.dims = {136, 156, 50};
  s.landmark_count = 150;
  return s;
}

void for_each_voxel(const Grid3& g, const std::function<void(int, int, int)>& f) {
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) f(i, j, k);
}

// A threshold segmenter leaking into dura and fluid: the outline grown by
// `voxels` voxels along every axis (26-neighbourhood), as brain.
LabelImage leaked(const LabelImage& in, int voxels) {
  LabelImage out = in;
  const Grid3& g = in.grid;
  for (int round = 0; round < voxels; ++round) {
    const LabelImage prev = out;
    for_each_voxel(g, [&](int i, int j, int k) {
      if (prev.at(i, j, k) != 0) return;
      for (int dk = -1; dk <= 1; ++dk)
        for (int dj = -1; dj <= 1; ++dj)
          for (int di = -1; di <= 1; ++di)
            if (g.contains(i + di, j + dj, k + dk) && prev.at(i + di, j + dj, k + dk) != 0) {
              out.at(i, j, k) = 1;
              return;
            }
    });
  }
  return out;
}

Eigen::Vector3d centroid(const LabelImage& l) {
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  double n = 0;
  for_each_voxel(l.grid, [&](int i, int j, int k) {
    if (l.at(i, j, k) != 0) c += l.grid.world_mm(i, j, k), n += 1;
  });
  return c / n;
}

template <class T>
Image3<T> flipped_first_axis(const Image3<T>& in) {
  Image3<T> out = in;
  const auto& d = in.grid.dims;
  for_each_voxel(in.grid, [&](int i, int j, int k) { out.at(i, j, k) = in.at(d[0] - 1 - i, j, k); });
  return out;
}

// A fallback's result with the affine it refused (metrics.affine.
// refused_intraop_from_preop) in place of the transform it delivered: what
// the fallback would have been without its rigid or image-based transform.
void expect_rigid(const Eigen::Matrix4d& intraop_from_preop) {
  const Eigen::Matrix3d R = intraop_from_preop.topLeftCorner<3, 3>();
  EXPECT_NEAR(R.determinant(), 1.0, 1e-9);
  EXPECT_LT((R.transpose() * R - Eigen::Matrix3d::Identity()).norm(), 1e-9);
}

ScanResult with_refused_affine(const ScanResult& r) {
  ScanResult refused = r;
  const auto& rows = r.metrics["affine"]["refused_intraop_from_preop"];
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) refused.intraop_from_preop(i, j) = rows[i][j].get<double>();
  return refused;
}

struct Outcome {
  std::string how;  // "refused: ...", "input error: ...", or "nonrigid"
  bool refused = false;
  double affine_mm = 0, nonrigid_mm = 0;
};

class DamagedInputs : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    preop_ = new PreopInput(asymmetric_head());
    session_ = new EngineSession(MPI_COMM_WORLD, coarse_parameters());
    session_->load_preop(*preop_, nullptr);
    case_ = new PhantomCase(make_phantom(preop_->t1, preop_->labels, spec()));
  }
  static void TearDownTestSuite() {
    delete case_;
    delete session_;
    delete preop_;
  }
  static Outcome run(const std::string& name, const IntraopInput& scan) {
    Outcome o;
    try {
      const ScanResult r = session_->register_scan(scan, nullptr);
      const auto e = evaluation::evaluate_result(name, *case_, r);
      o.affine_mm = e.affine_mean_mm;
      o.nonrigid_mm = e.nonrigid_mean_mm;
      o.refused = r.kind != ResultKind::nonrigid;
      o.how = o.refused ? "refused: " + r.fallback_reason : "nonrigid";
      last_metrics_ = r.metrics;
      for (const auto& [gate, g] : r.metrics["plausibility"].items())
        if (g.is_object() && g.value("tested", false) && !g.value("passed", true)) o.how += " [gate " + gate + " failed]";
    } catch (const InputError& e) {
      o.refused = true;
      o.how = std::string("input error: ") + e.what();
    }
    std::printf("%-34s %-5s affine %5.2f non-rigid %5.2f mm | %s\n", name.c_str(), scan.t1 ? "+T1" : "", o.affine_mm,
                o.nonrigid_mm, o.how.c_str());
    return o;
  }
  // Refused, or a non-rigid answer no worse than the affine alone.
  static void expect_not_silent(const std::string& name, const IntraopInput& scan) {
    const Outcome o = run(name, scan);
    if (!o.refused) {
      EXPECT_LE(o.nonrigid_mm, o.affine_mm + 0.05) << name << ": a silent non-rigid failure";
    }
  }
  // gates: the plausibility gates of which at least one must have failed
  // (whatever else refused the scan first).
  static void expect_refused(const std::string& name, const IntraopInput& scan, std::vector<std::string> gates) {
    const Outcome o = run(name, scan);
    EXPECT_TRUE(o.refused) << name << ": accepted as non-rigid (" << o.nonrigid_mm << " mm against the affine's "
                           << o.affine_mm << ")";
    if (o.how.rfind("input error", 0) == 0) return;
    const auto& p = last_metrics_["plausibility"];
    bool tripped = false;
    for (const auto& g : gates) tripped |= p.contains(g) && p[g].value("tested", false) && !p[g].value("passed", true);
    EXPECT_TRUE(tripped) << name << ": none of the expected gates failed: " << p.dump(1);
  }
  // A fallback's field is its transform's, and that transform lies nearer
  // the truth than the affine it refused, by more than margin_mm.
  static void expect_nearer_than_the_refused_affine(const ScanResult& r, double margin_mm) {
    const auto delivered = evaluation::evaluate_result("delivered", *case_, r);
    const auto refused = evaluation::evaluate_result("refused affine", *case_, with_refused_affine(r));
    EXPECT_NEAR(delivered.nonrigid_mean_mm, delivered.affine_mean_mm, 0.05);
    EXPECT_LT(delivered.nonrigid_mean_mm, refused.affine_mean_mm - margin_mm)
        << delivered.nonrigid_mean_mm << " vs " << refused.affine_mean_mm;
  }
  static IntraopInput both(LabelImage labels, ImageF t1) { return {std::move(labels), std::move(t1)}; }
  // Labels with the case's image, through the engine's whole path for a
  // pushed scan (the labels-vs-image check; refused labels refined give way
  // to the image's own answer, used exactly to a fallback on the image).
  static ScanResult register_with_the_image(LabelImage labels, GivenLabelsUse use = GivenLabelsUse::refine) {
    ScanInput scan;
    scan.labels = std::move(labels);
    scan.image = case_->intraop_t1;
    scan.labels_use = use;
    return session_->register_scan(scan, nullptr);
  }
  static IntraopInput labels_only(LabelImage labels) { return {std::move(labels), std::nullopt}; }

  static PreopInput* preop_;
  static EngineSession* session_;
  static PhantomCase* case_;
  static nlohmann::json last_metrics_;
};
PreopInput* DamagedInputs::preop_ = nullptr;
EngineSession* DamagedInputs::session_ = nullptr;
PhantomCase* DamagedInputs::case_ = nullptr;
nlohmann::json DamagedInputs::last_metrics_;

}  // namespace

TEST_F(DamagedInputs, TheUndamagedScanPassesEveryGate) {
  for (const auto& scan : {both(case_->intraop_labels, case_->intraop_t1), labels_only(case_->intraop_labels)}) {
    const Outcome o = run("undamaged", scan);
    EXPECT_FALSE(o.refused) << o.how;
    EXPECT_LT(o.nonrigid_mm, o.affine_mm);
    EXPECT_EQ(last_metrics_["plausibility"]["all_passed"], true) << last_metrics_["plausibility"].dump(1);
    for (const char* gate : {"volume", "affine_stretch", "head_rotation", "left_right", "strain", "max_displacement"})
      EXPECT_TRUE(last_metrics_["plausibility"][gate]["tested"].get<bool>()) << gate;
  }
}

TEST_F(DamagedInputs, AnOutlineLeakingFourVoxelsIn3DIsRefused) {
  const LabelImage leak = leaked(case_->intraop_labels, 4);
  expect_refused("leak 4 voxels 3D", both(leak, case_->intraop_t1), {"volume", "affine_stretch"});
  expect_refused("leak 4 voxels 3D", labels_only(leak), {"volume", "affine_stretch"});
}

// A refused scan's answer is the affine alone (here its rigid part, the
// leak having stretched the affine fitted to it): its uncertainty map
// carries the surface residual that transform leaves through the model, not
// the non-rigid floor. The fallback is marked; the map does not make it
// trustworthy.
TEST_F(DamagedInputs, ARefusedScansMapCarriesTheResidualTheAffineLeaves) {
  const IntraopInput scan = labels_only(leaked(case_->intraop_labels, 4));
  ScanResult r = session_->register_scan(scan, nullptr);
  ASSERT_NE(r.kind, ResultKind::nonrigid);
  session_->add_uncertainty(scan, r, nullptr);
  const nlohmann::json& u = r.metrics["uncertainty"];
  EXPECT_GT(u["samples"].get<int>(), 0);
  const double floor_mm = kBand95PerRms * u["quantisation_rms_mm"].get<double>();
  EXPECT_GT(u["band95_mm"]["median"].get<double>(), 2 * floor_mm) << u.dump();
}

// Labels refused for their own geometry (a leak stretches the affine fitted
// to them by a quarter): the fallback delivers the affine's rigid part, since
// a head does not swell, and it lies nearer the truth than the refused
// affine does.
TEST_F(DamagedInputs, ARefusalOfTheLabelsGeometryDeliversTheAffinesRigidPart) {
  const ScanResult r = session_->register_scan(labels_only(leaked(case_->intraop_labels, 4)), nullptr);
  ASSERT_EQ(r.kind, ResultKind::affine_only_fallback);
  ASSERT_TRUE(r.metrics["affine"].contains("fallback_transform")) << r.metrics["affine"].dump();
  expect_rigid(r.intraop_from_preop);
  const ScanResult refused = with_refused_affine(r);
  const double refused_scale = refused.intraop_from_preop.topLeftCorner<3, 3>().determinant();
  EXPECT_GT(refused_scale, 1.2) << "the leak no longer stretches";
  expect_nearer_than_the_refused_affine(r, 1.0);
}

// A leak pushed with its image to be used exactly: the labels-vs-image
// check refuses it before any gate, and the affine fitted to it is
// stretched, so the fallback is a rigid transform from the image's own
// segmentation (docs/DESIGN.md "Quality gates").
TEST_F(DamagedInputs, LabelsAtOddsWithTheirImageFallBackToARigidTransformFromTheImage) {
  const ScanResult r = register_with_the_image(leaked(case_->intraop_labels, 3), GivenLabelsUse::exact);
  ASSERT_EQ(r.kind, ResultKind::affine_only_fallback);
  ASSERT_NE(r.fallback_reason.find("disagree with the intraop image"), std::string::npos)
      << r.fallback_reason << r.metrics["label_image_check"].dump();
  EXPECT_EQ(r.metrics["affine"].value("fallback_transform", ""),
            "rigid part of the affine registered on the intraop image's own segmentation (the labels disagree with "
            "their image)");
  expect_rigid(r.intraop_from_preop);
  expect_nearer_than_the_refused_affine(r, 1.0);
}

// Labels of the scan moved 10 mm (a segmentation of another series, or
// saved with another header), to be used exactly: the check refuses them,
// and the affine fitted to them carries the shift, rigid part and all. The
// fallback registers the image's own segmentation instead, so it lies where
// the brain does.
TEST_F(DamagedInputs, LabelsShiftedFromTheirImageFallBackToTheImagesOwnAffine) {
  LabelImage moved(case_->intraop_labels.grid, 0);
  const Grid3& g = moved.grid;
  const int shift_voxels = static_cast<int>(std::lround(10.0 / g.spacing_mm().y()));
  for_each_voxel(g, [&](int i, int j, int k) {
    if (j >= shift_voxels) moved.at(i, j, k) = case_->intraop_labels.at(i, j - shift_voxels, k);
  });
  const ScanResult r = register_with_the_image(std::move(moved), GivenLabelsUse::exact);
  ASSERT_EQ(r.kind, ResultKind::affine_only_fallback);
  ASSERT_NE(r.fallback_reason.find("disagree with the intraop image"), std::string::npos) << r.fallback_reason;
  const ScanResult refused = with_refused_affine(r);
  const auto delivered = evaluation::evaluate_result("from the image", *case_, r);
  const auto shifted = evaluation::evaluate_result("labels' affine", *case_, refused);
  EXPECT_GT(shifted.affine_mean_mm, 7.0) << "the labels' affine no longer carries the shift";
  EXPECT_LT(delivered.nonrigid_mean_mm, 4.0) << delivered.nonrigid_mean_mm << " vs " << shifted.affine_mean_mm
                                             << r.metrics["affine"].dump();
}

// Labels whose geometry the gates refuse, pushed with their image to be used
// exactly (the leak of four voxels stretches their affine beyond the
// affine_stretch gate): the image says where the brain is, so the fallback
// is the rigid part of the image's own affine, and the gate's reason stands.
TEST_F(DamagedInputs, AGeometryRefusalWithItsImageFallsBackToTheImagesOwnAffine) {
  const ScanResult r = register_with_the_image(leaked(case_->intraop_labels, 4), GivenLabelsUse::exact);
  ASSERT_EQ(r.kind, ResultKind::affine_only_fallback);
  ASSERT_EQ(r.fallback_reason.rfind("plausibility gate", 0), 0u) << r.fallback_reason;
  EXPECT_EQ(r.metrics["affine"].value("fallback_transform", ""),
            "rigid part of the affine registered on the intraop image's own segmentation (the labels' geometry was "
            "refused)");
  expect_rigid(r.intraop_from_preop);
  expect_nearer_than_the_refused_affine(r, 1.0);
}

// The same refusals of labels to be refined by their image (the default):
// the site asked for the image's judgement, so the answer is the image's
// own (an image-only scan's), non-rigid, as near the truth as an image
// alone gets, and never clean: it carries a caution naming the refusal.
TEST_F(DamagedInputs, RefusedLabelsToBeRefinedGiveWayToTheImagesOwnAnswer) {
  LabelImage moved(case_->intraop_labels.grid, 0);
  const int shift_voxels = static_cast<int>(std::lround(10.0 / moved.grid.spacing_mm().y()));
  for_each_voxel(moved.grid, [&](int i, int j, int k) {
    if (j >= shift_voxels) moved.at(i, j, k) = case_->intraop_labels.at(i, j - shift_voxels, k);
  });
  ScanInput alone;
  alone.image = case_->intraop_t1;
  const ScanResult image_alone = session_->register_scan(alone, nullptr);
  ASSERT_EQ(image_alone.kind, ResultKind::nonrigid) << image_alone.fallback_reason;
  const double image_alone_mm = evaluation::evaluate_result("image alone", *case_, image_alone).nonrigid_mean_mm;
  struct Refused {
    const char* name;
    LabelImage labels;
    const char* why;
  };
  // (The leak of four voxels, refused for its geometry when used exactly, is
  // refused by the check first here.)
  for (const Refused& d : {Refused{"leak 3 voxels", leaked(case_->intraop_labels, 3), "disagree with their image"},
                           Refused{"moved 10 mm", moved, "disagree with their image"},
                           Refused{"leak 4 voxels", leaked(case_->intraop_labels, 4), "disagree with their image"}}) {
    const ScanResult r = register_with_the_image(d.labels);
    ASSERT_EQ(r.kind, ResultKind::nonrigid) << d.name << ": " << r.fallback_reason;
    const nlohmann::json& given = r.metrics["given_labels"];
    EXPECT_TRUE(given.value("disregarded", false)) << d.name << given.dump();
    EXPECT_NE(given.value("why", "").find(d.why), std::string::npos) << d.name << given.dump();
    EXPECT_NE(result_caution(r.metrics).find("the given labels were disregarded"), std::string::npos) << d.name;
    ASSERT_TRUE(r.intraop_labels) << d.name << ": the image's segmentation is the answer's";
    const double mm = evaluation::evaluate_result(d.name, *case_, r).nonrigid_mean_mm;
    EXPECT_NEAR(mm, image_alone_mm, 0.05) << d.name;
  }
}

// A segmenter that lost the left ventricle's posterior horn (its voxels
// labelled brain), pushed with the image to be refined: no deformation of
// the preop's ventricles reaches what is left (the residual gate refuses
// the labels' own pass), which says something against the labels, so the
// image's own answer stands, with the caution; used exactly, the marked
// fallback.
TEST_F(DamagedInputs, LabelsMissingAVentricleToBeRefinedGiveWayToTheImagesOwnAnswer) {
  LabelImage lost = case_->intraop_labels;
  const Eigen::Vector3d c = centroid(lost);
  for_each_voxel(lost.grid, [&](int i, int j, int k) {
    const Eigen::Vector3d p = lost.grid.world_mm(i, j, k);
    if (lost.at(i, j, k) == 2 && p.x() < c.x() && p.y() < c.y() - 5) lost.at(i, j, k) = 1;
  });
  const ScanResult exact = register_with_the_image(lost, GivenLabelsUse::exact);
  ASSERT_EQ(exact.kind, ResultKind::affine_only_fallback) << "the lost ventricle was matched";
  ASSERT_NE(exact.fallback_reason.find("surface match of ventricles diverged"), std::string::npos)
      << exact.fallback_reason << exact.metrics["label_image_check"].dump();
  const ScanResult r = register_with_the_image(lost);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason;
  const nlohmann::json& given = r.metrics["given_labels"];
  EXPECT_TRUE(given.value("disregarded", false)) << given.dump();
  EXPECT_NE(given.value("why", "").find("no deformation of the preop reaches their ventricles"), std::string::npos)
      << given.dump();
  EXPECT_NE(result_caution(r.metrics).find("the given labels were disregarded"), std::string::npos);
  ScanInput alone;
  alone.image = case_->intraop_t1;
  const double image_alone_mm =
      evaluation::evaluate_result("image alone", *case_, session_->register_scan(alone, nullptr)).nonrigid_mean_mm;
  EXPECT_NEAR(evaluation::evaluate_result("lost ventricle", *case_, r).nonrigid_mean_mm, image_alone_mm, 0.05);
}

TEST_F(DamagedInputs, ALost45MillimetreBlockIsNotASilentFailure) {
  LabelImage lost = case_->intraop_labels;
  const Eigen::Vector3d c = centroid(lost) + Eigen::Vector3d(38, 0, 0);
  for_each_voxel(lost.grid, [&](int i, int j, int k) {
    if (((lost.grid.world_mm(i, j, k) - c).cwiseAbs().array() < 22.5).all()) lost.at(i, j, k) = 0;
  });
  expect_not_silent("lost 45 mm block", both(lost, case_->intraop_t1));
  expect_not_silent("lost 45 mm block", labels_only(lost));
}

TEST_F(DamagedInputs, MirroredLabelsAndImageAreRefused) {
  const LabelImage labels = flipped_first_axis(case_->intraop_labels);
  expect_refused("mirrored left-right", both(labels, flipped_first_axis(case_->intraop_t1)), {"left_right"});
  expect_refused("mirrored left-right", labels_only(labels), {"left_right"});
}

TEST_F(DamagedInputs, AScanOfAnotherHeadIsRefused) {
  // Another, smaller head: the scan's anatomy scaled by 0.86 about its
  // centroid and bent by a smooth 3 mm warp.
  const Eigen::Vector3d c = centroid(case_->intraop_labels);
  Eigen::Matrix4d source_from_target = Eigen::Matrix4d::Identity();
  source_from_target.topLeftCorner<3, 3>() /= 0.86;
  source_from_target.block<3, 1>(0, 3) = c - c / 0.86;
  const LabelImage labels = resample_nearest(case_->intraop_labels, case_->intraop_labels.grid, source_from_target);
  const ImageF t1 = resample_linear(case_->intraop_t1, case_->intraop_t1.grid, source_from_target);
  expect_refused("another head", both(labels, t1), {"affine_stretch", "volume"});
  expect_refused("another head", labels_only(labels), {"affine_stretch", "volume"});
}

TEST_F(DamagedInputs, SwappedVentricleAndBrainLabelsAreRefused) {
  LabelImage swapped = case_->intraop_labels;
  for (auto& v : swapped.voxels) v = v == 1 ? 2 : v == 2 ? 1 : v;
  expect_refused("ventricle and brain labels swapped", both(swapped, case_->intraop_t1), {"ventricle_volume"});
  expect_refused("ventricle and brain labels swapped", labels_only(swapped), {"ventricle_volume"});
}

TEST_F(DamagedInputs, ASegmentationOneSliceOutOfStepIsNotASilentFailure) {
  LabelImage shifted(case_->intraop_labels.grid, 0);
  for_each_voxel(shifted.grid, [&](int i, int j, int k) {
    if (k > 0) shifted.at(i, j, k) = case_->intraop_labels.at(i, j, k - 1);
  });
  expect_not_silent("labels one slice out of step", both(shifted, case_->intraop_t1));
}
