// An intraop field of view that cuts the brain (a slab, a short coil, an
// oblique block that misses the base): the part out of view is not missing
// tissue, and the plausibility volume gate (quality/plausibility_gates.h)
// compares only the preop brain the affine places in view. On the small
// synthetic head (coarse mesh).
#include <gtest/gtest.h>
#include <mpi.h>

#include <algorithm>
#include <cmath>
#include <string>

#include "coarse_parameters.h"  // tests/support
#include "core/errors.h"
#include "pipeline/engine_session.h"
#include "synthetic_head.h"

using namespace brainshift;

namespace {

// The preop labels on an iMRI-like grid (1.4 x 1.4 x 2.8 mm) moved by a
// translation, the grid starting `cut_fraction` of the brain's height above
// its base; the top 6 mm of a 30 mm disc removed (a sinking).
IntraopInput cut_scan(const PreopInput& preop, const Eigen::Vector3d& shift_mm, double cut_fraction) {
  double bottom = 1e9, top = -1e9;
  const Grid3& pg = preop.labels.grid;
  for (int k = 0; k < pg.dims[2]; ++k)
    for (int j = 0; j < pg.dims[1]; ++j)
      for (int i = 0; i < pg.dims[0]; ++i)
        if (preop.labels.at(i, j, k)) {
          bottom = std::min(bottom, pg.world_mm(i, j, k).z() + shift_mm.z());
          top = std::max(top, pg.world_mm(i, j, k).z() + shift_mm.z());
        }
  const double z0 = bottom + cut_fraction * (top - bottom);
  Grid3 g;
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  g.world_from_voxel.diagonal().head<3>() = Eigen::Vector3d(1.4, 1.4, 2.8);
  g.world_from_voxel.block<3, 1>(0, 3) = Eigen::Vector3d(-70, -77, z0);
  g.dims = {100, 110, static_cast<int>((top + 15 - z0) / 2.8)};
  test::MovedHead moved = test::move_head(preop.labels, preop.t1, g, shift_mm);
  IntraopInput scan{std::move(moved.labels), std::move(moved.t1)};
  test::sink_top(scan.labels, 6.0, 30.0);
  return scan;
}

// The synthetic head's preop, warm on a coarse mesh.
class FieldOfView : public ::testing::Test {
 protected:
  FieldOfView() : preop{head().t1, head().labels}, session(MPI_COMM_WORLD, test::coarse_parameters()) {
    session.load_preop(preop, nullptr);
  }
  static const test::SyntheticHead& head() {
    static const test::SyntheticHead h = test::synthetic_head();
    return h;
  }
  const PreopInput preop;
  EngineSession session;
  const Eigen::Vector3d shift{1.0, -1.0, 0.5};
};

TEST_F(FieldOfView, ABrainCutByTheFieldOfViewIsNotALostLobe) {
  // The lower 35 % of the brain's height (some 28 % of its volume) out of view.
  const IntraopInput scan = cut_scan(preop, shift, 0.35);
  const ScanResult r = session.register_scan(scan, nullptr);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason;
  const auto& volume = r.metrics["plausibility"]["volume"];
  ASSERT_TRUE(volume["tested"].get<bool>()) << volume.dump();
  const double in_view = volume["preop_fraction_in_view"].get<double>();
  EXPECT_GT(in_view, 0.60) << volume.dump();
  EXPECT_LT(in_view, 0.85) << volume.dump();
  // Against the whole preop brain the cut alone would be a change of 1 - in_view.
  EXPECT_GT(1.0 - in_view, PipelineParameters{}.plausibility.max_volume_change);
  // The cut changes the gate's value little: the same scan with the whole
  // brain in view (the sinking's own loss and the labels' staircase).
  const ScanResult whole = session.register_scan(cut_scan(preop, shift, -0.1), nullptr);
  const auto& whole_volume = whole.metrics["plausibility"]["volume"];
  EXPECT_NEAR(whole_volume["preop_fraction_in_view"].get<double>(), 1.0, 1e-9);
  EXPECT_NEAR(volume["value"].get<double>(), whole_volume["value"].get<double>(), 0.03)
      << volume.dump() << "\n" << whole_volume.dump();
  // The translation is recovered where the brain did not sink.
  const Grid3& g = scan.labels.grid;
  double sum = 0;
  std::size_t n = 0;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        if (scan.labels.at(i, j, k) == 0 || g.world_mm(i, j, k).head<2>().norm() < 40.0) continue;
        sum += (r.pullback_field_mm.vectors[g.index(i, j, k)].cast<double>() + shift).norm();
        ++n;
      }
  ASSERT_GT(n, 1000u);
  EXPECT_LT(sum / static_cast<double>(n), 0.5);
}

// The uncertainty map says where the scan showed nothing: the band is wide
// next to the cut (the brain beyond it may have moved unseen) and back to
// what the seen data give far from it; with the whole brain in view no
// surface is unseen and nothing is added.
TEST_F(FieldOfView, TheUncertaintyMapIsWideAtTheCut) {
  const IntraopInput scan = cut_scan(preop, shift, 0.35);
  ScanResult r = session.register_scan(scan, nullptr);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason;
  session.add_uncertainty(scan, r, nullptr);
  const auto& unseen = r.metrics["uncertainty"]["unseen_surface"];
  EXPECT_GT(unseen["fixed_nodes"].get<int>(), 0) << unseen.dump();
  // The band in brain voxels within 3 mm of the cut (the grid's lowest face)
  // and farther than 40 mm from it.
  const Grid3& g = scan.labels.grid;
  std::vector<double> at_cut, far;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        if (scan.labels.at(i, j, k) == 0) continue;
        const double above_cut_mm = k * g.spacing_mm().z();
        const double band = r.uncertainty_mm.at(i, j, k);
        if (above_cut_mm < 3.0) at_cut.push_back(band);
        else if (above_cut_mm > 40.0) far.push_back(band);
      }
  ASSERT_GT(at_cut.size(), 100u);
  ASSERT_GT(far.size(), 100u);
  const auto median = [](std::vector<double> v) {
    std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
    return v[v.size() / 2];
  };
  EXPECT_GT(median(at_cut), 3.0) << "far from the cut " << median(far);
  EXPECT_GT(median(at_cut), 3.0 * median(far)) << "at the cut " << median(at_cut);
  // The whole brain in view: nothing unseen.
  const IntraopInput whole_scan = cut_scan(preop, shift, -0.1);
  ScanResult whole = session.register_scan(whole_scan, nullptr);
  session.add_uncertainty(whole_scan, whole, nullptr);
  EXPECT_EQ(whole.metrics["uncertainty"]["unseen_surface"]["fixed_nodes"].get<int>(), 0);
}

// An image that holds a fifth of the brain: refused before the segmentation,
// said of the image, as given labels are (PipelineTest's bad inputs).
TEST_F(FieldOfView, AnImageThatMissesMostOfTheBrainIsAClearError) {
  ScanInput scan;
  scan.image = test::scanner_image(*cut_scan(preop, {0, 0, 0}, 0.7).t1);
  try {
    session.register_scan(scan, nullptr);
    ADD_FAILURE() << "accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("intraop image: the field of view holds"), std::string::npos) << e.what();
  }
  // The session keeps serving.
  scan.image = test::scanner_image(*cut_scan(preop, {0, 0, 0}, -0.1).t1);
  EXPECT_EQ(session.register_scan(scan, nullptr).kind, ResultKind::nonrigid);
}

// An image shifted below zero on its way here (a z-scored export: air at
// about -1 instead of 0) was taken for one that misses most of the brain:
// the head mask and the classifier read intensities as a magnitude image's.
// It is lifted back (image/intensity_offset.h) and registers as the image
// itself does; the metrics say by how much.
TEST_F(FieldOfView, AnImageShiftedBelowZeroRegistersAsTheImageItself) {
  ScanInput plain;
  plain.image = test::scanner_image(*cut_scan(preop, shift, -0.1).t1);
  const ScanResult a = session.register_scan(plain, nullptr);
  ASSERT_EQ(a.kind, ResultKind::nonrigid) << a.fallback_reason;
  EXPECT_FALSE(a.metrics.contains("intensity_lift"));
  ScanInput z_scored = plain;
  double sum = 0, sum2 = 0;
  for (float v : z_scored.image->voxels) sum += v, sum2 += static_cast<double>(v) * v;
  const double n = static_cast<double>(z_scored.image->voxels.size()), mean = sum / n;
  const double sd = std::sqrt(sum2 / n - mean * mean);
  for (float& v : z_scored.image->voxels) v = static_cast<float>((v - mean) / sd);
  const ScanResult b = session.register_scan(z_scored, nullptr);
  ASSERT_EQ(b.kind, ResultKind::nonrigid) << b.fallback_reason;
  EXPECT_GT(b.metrics["intensity_lift"]["intraop"].get<double>(), 0.5) << b.metrics["intensity_lift"].dump();
  EXPECT_EQ(b.metrics["intensity_lift"]["preop_t1"].get<double>(), 0.0);
  // The same answer to a fraction of a voxel over the brain.
  const Grid3& g = a.pullback_field_mm.grid;
  ASSERT_TRUE(g.same_geometry(b.pullback_field_mm.grid));
  double differs = 0;
  std::size_t voxels = 0;
  for (std::size_t v = 0; v < g.voxel_count(); ++v) {
    if (!a.intraop_labels || a.intraop_labels->voxels[v] == 0) continue;
    differs += (a.pullback_field_mm.vectors[v] - b.pullback_field_mm.vectors[v]).norm();
    ++voxels;
  }
  ASSERT_GT(voxels, 1000u);
  EXPECT_LT(differs / static_cast<double>(voxels), 0.1);
}

}  // namespace
