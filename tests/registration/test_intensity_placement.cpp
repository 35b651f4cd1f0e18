// The preop placed on a scan by intensity (registration/intensity_placement.h):
// the brain-extracted Colin27 T1 (ch2bet, as a planning system stores a
// preop) placed on the whole head (ch2) moved by a known rigid transform,
// on an intraop-like grid (1.5 x 1.5 x 3 mm, tilted) with noise, must come
// back within a millimetre and a degree; a T2-like scan (the intensities
// turned over, fluid bright) as well; a scan that shows another place
// entirely is not placed well (its correlation says so).
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>

#include "image/morphology.h"
#include "image/nifti_io.h"
#include "image/resample.h"
#include "registration/intensity_placement.h"
#include "synthetic.h"

namespace brainshift {
namespace {

const std::filesystem::path kBrain = "/usr/share/mricron/templates/ch2bet.nii.gz";
const std::filesystem::path kHead = "/usr/share/mricron/templates/ch2.nii.gz";

// The largest displacement of the preop brain's bounding-box corners
// between two placements: the worst error anywhere in the brain.
double corner_error_mm(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b) {
  double worst = 0;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector4d p((c & 1) ? 70 : -70, (c & 2) ? 70 : -105, (c & 4) ? 80 : -45, 1);
    worst = std::max(worst, ((a - b) * p).head<3>().norm());
  }
  return worst;
}

class IntensityPlacementTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!std::filesystem::exists(kBrain) || !std::filesystem::exists(kHead))
      GTEST_SKIP() << "mricron-data's Colin27 templates are not installed";
    preop = read_scalar_image(kBrain);
    brain = largest_component(threshold(preop, 1e-3f, 1e30f), 6);
    head = read_scalar_image(kHead);
  }
  // The whole head moved by truth (intraop = truth * preop), on a tilted
  // intraop grid, with noise (sd 2 % of the head's range).
  ImageF scan(const Eigen::Matrix4d& truth, bool t2_like) const {
    const Eigen::Matrix3d tilt =
        Eigen::AngleAxisd(10 * M_PI / 180, Eigen::Vector3d(1, 0.3, 0).normalized()).toRotationMatrix();
    const Grid3 grid = test::make_grid({130, 150, 60}, {1.5, 1.5, 3.0}, tilt, (truth * Eigen::Vector4d(0, -18, 18, 1)).head<3>());
    ImageF out = resample_linear(head, grid, truth.inverse());
    const float top = *std::max_element(out.voxels.begin(), out.voxels.end());
    std::uint32_t state = 12345u;
    for (float& v : out.voxels) {
      if (t2_like && v > 0.05f * top) v = top - v;  // fluid bright, tissue dark, air dark
      state = state * 1664525u + 1013904223u;
      v += 0.02f * top * (static_cast<float>(state >> 8) / static_cast<float>(1u << 24) - 0.5f) * 3.46f;
      v = std::max(v, 0.f);
    }
    return out;
  }
  ImageF preop, head;
  Mask brain;
};

Eigen::Matrix4d rigid(const Eigen::Vector3d& axis, double deg, const Eigen::Vector3d& t) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topLeftCorner<3, 3>() = Eigen::AngleAxisd(deg * M_PI / 180, axis.normalized()).toRotationMatrix();
  m.topRightCorner<3, 1>() = t;
  return m;
}

TEST_F(IntensityPlacementTest, ABrainExtractedPreopIsPlacedOnAWholeHeadWithinAMillimetre) {
  for (const bool t2_like : {false, true}) {
    SCOPED_TRACE(t2_like ? "T2-like scan" : "T1 scan");
    const Eigen::Matrix4d truth = rigid({0.3, -0.5, 1}, 7, {9, -6, 7});
    const IntensityPlacement r = place_by_intensity(preop, brain, scan(truth, t2_like), Eigen::Matrix4d::Identity());
    EXPECT_LT(corner_error_mm(r.intraop_from_preop, truth), 1.0) << r.message << "\n" << r.intraop_from_preop;
    EXPECT_GT(std::abs(r.correlation), 0.6) << r.message;
    EXPECT_EQ(r.correlation < 0, t2_like) << r.message;
    const double det = r.intraop_from_preop.topLeftCorner<3, 3>().determinant();
    EXPECT_NEAR(det, 1.0, 1e-9) << "rigid by default";
    EXPECT_LE(r.evaluations, 2 * IntensityPlacementParameters{}.max_evaluations + 2);
  }
}

TEST_F(IntensityPlacementTest, ATranslationBeyondItsReachIsNotFoundAndSaysSo) {
  // 60 mm away (beyond the 4 mm level's reach): whatever it settles on
  // correlates far worse than a true placement does.
  const Eigen::Matrix4d truth = rigid({0, 0, 1}, 0, {60, 0, 0});
  const IntensityPlacement r = place_by_intensity(preop, brain, scan(truth, false), Eigen::Matrix4d::Identity());
  EXPECT_GT(corner_error_mm(r.intraop_from_preop, truth), 10.0);
  EXPECT_LT(std::abs(r.correlation), 0.6) << r.message;
}

TEST_F(IntensityPlacementTest, AHeadTurnedInItsClampIsFoundByThePoseSearch) {
  // A lateral approach: the head turned 90 degrees about S-I and flexed 20
  // in the scanner, which its RAS does not follow. From the scanner's
  // placement the local search cannot reach it; the pose search can.
  const Eigen::Matrix4d turn = rigid({0, 0, 1}, 90, {12, -8, 15}) * rigid({1, 0, 0}, 20, {0, 0, 0});
  const IntensityPlacementPreop samples = intensity_placement_preop(preop, brain);
  const IntensityPlacementScan image = intensity_placement_scan(samples, scan(turn, false));
  const IntensityPlacement local = place_by_intensity(samples, image, Eigen::Matrix4d::Identity());
  EXPECT_GT(corner_error_mm(local.intraop_from_preop, turn), 10.0) << "beyond the local search's reach";
  const PoseSearch search = search_pose_by_intensity(samples, image, Eigen::Matrix4d::Identity());
  EXPECT_GT(search.rotation_from_start_deg, 60.0);
  EXPECT_EQ(search.candidates, 108);
  EXPECT_LE(search.evaluations, search.candidates * (IntensityPlacementParameters{}.pose_evaluations + 1));
  const IntensityPlacement found = place_by_intensity(samples, image, search.intraop_from_preop);
  EXPECT_LT(corner_error_mm(found.intraop_from_preop, turn), 1.0) << found.message;
  EXPECT_GT(found.correlation * found.correlation, local.correlation * local.correlation);
  // The correlation at a placement is the one the placement reports.
  EXPECT_NEAR(intensity_correlation(samples, image, found.intraop_from_preop), found.correlation, 1e-9);
}

}  // namespace
}  // namespace brainshift
