// The gates of the automatic path (pipeline/prepare_stage.h
// check_segmentation) on segmentations whose faults are known: a brain far
// larger or smaller than the preop's, no ventricles, an uncertain outer
// surface. Each must be refused with its reason; a sound one passes.
#include <gtest/gtest.h>

#include "config_file.h"
#include "core/errors.h"
#include "pipeline/prepare_stage.h"
#include "pipeline/segmentation_rounds.h"

using namespace brainshift;

namespace {

// A brain ellipsoid (60, 70, 50 mm) with two ventricle ellipsoids, on a 2 mm grid.
LabelImage head(double brain_scale, bool ventricles) {
  Grid3 g;
  g.dims = {90, 100, 80};
  g.world_from_voxel.diagonal().head<3>() = Eigen::Vector3d(2, 2, 2);
  g.world_from_voxel.block<3, 1>(0, 3) = Eigen::Vector3d(-90, -100, -80);
  LabelImage l(g, 0);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d p = g.world_mm(i, j, k);
        const double r = (p.array() / (brain_scale * Eigen::Array3d(60, 70, 50))).matrix().norm();
        const double rv = ((p - Eigen::Vector3d(std::copysign(10.0, p.x()), 0, 8)).array() /
                           Eigen::Array3d(6, 22, 8)).matrix().norm();
        if (r < 1) l.at(i, j, k) = ventricles && rv < 1 ? 2 : 1;
      }
  return l;
}

const LabelTable& table() { return config::default_label_table(); }

SegmentationGates gates(const LabelImage& seg, float confidence) {
  return check_segmentation(seg, ImageF(seg.grid, confidence), head(1.0, true), table(),
                            AutoSegmentationParameters{});
}

}  // namespace

TEST(SegmentationGates, ASoundSegmentationPasses) {
  const auto g = gates(head(1.01, true), 0.95f);
  EXPECT_TRUE(g.failure.empty()) << g.failure << g.metrics.dump();
  EXPECT_TRUE(g.metrics["passed"].get<bool>());
}

TEST(SegmentationGates, ABrainFarFromThePreopsVolumeIsRefused) {
  // 1.08^3 = +26 %: a leak into the fluid and dura all round.
  const auto big = gates(head(1.08, true), 0.95f);
  EXPECT_NE(big.failure.find("volume"), std::string::npos) << big.metrics.dump();
  // 0.9^3 = -27 %: a lost lobe (the default table's resectable tumour is absent here).
  const auto small = gates(head(0.9, true), 0.95f);
  EXPECT_NE(small.failure.find("volume"), std::string::npos) << small.metrics.dump();
}

TEST(SegmentationGates, NoVentriclesIsRefused) {
  const auto g = gates(head(1.0, false), 0.95f);
  EXPECT_NE(g.failure.find("no ventricles"), std::string::npos) << g.failure << g.metrics.dump();
}

TEST(SegmentationGates, AnUncertainOuterSurfaceIsRefused) {
  const auto g = gates(head(1.0, true), 0.5f);
  EXPECT_NE(g.failure.find("uncertain"), std::string::npos) << g.failure << g.metrics.dump();
}

// A sinking replaces brain by the fluid found in its gap: a brain 15 % smaller
// than the preop's passes when that fluid was found (its volume given), and
// is refused when it was not (a lost lobe is tissue, never that fluid).
TEST(SegmentationGates, TheGapOfASinkingIsAllowedForByTheFluidFound) {
  const LabelImage preop = head(1.0, true), sunk = head(0.95, true);  // 0.95^3: -14 %
  double preop_ml = 0, sunk_ml = 0;
  for (std::size_t v = 0; v < preop.voxels.size(); ++v) {
    preop_ml += preop.voxels[v] != 0;
    sunk_ml += sunk.voxels[v] != 0;
  }
  const double gap_ml = (preop_ml - sunk_ml) * 8.0 / 1000;
  const auto check = [&](double open_fluid_ml) {
    return check_segmentation(sunk, ImageF(sunk.grid, 0.95f), preop, table(), AutoSegmentationParameters{},
                              open_fluid_ml);
  };
  const auto without = check(0);
  EXPECT_NE(without.failure.find("volume"), std::string::npos) << without.metrics.dump();
  const auto with_gap = check(gap_ml);
  EXPECT_TRUE(with_gap.failure.empty()) << with_gap.failure << with_gap.metrics.dump();
  EXPECT_DOUBLE_EQ(with_gap.metrics["brain_volume"]["open_fluid_ml"].get<double>(), gap_ml);
}

// The head's placement by the outline of the head scales by the two images'
// thresholds at the scalp's edge (5-8 % of volume on the robustness suite's
// images), not by the brain: the gates compare in the preop's own
// millilitres. The carried volumes divided by the placement's scale are the
// preop's own; a brain that lost 8 %, refused against the scaled reference,
// passes against the preop's own volume.
TEST(SegmentationGates, ThePlacementsScaleIsNotReadAsBrainLostOrGained) {
  const double axis_scale = 1.023, volume_scale = axis_scale * axis_scale * axis_scale;
  const LabelImage carried = head(axis_scale, true);  // the preop as a scaled placement carries it
  const CarriedPreopVolumes physical = carried_preop_volumes(carried, table(), volume_scale);
  const CarriedPreopVolumes as_placed = carried_preop_volumes(carried, table());
  EXPECT_NEAR(physical.brain_ml * volume_scale, as_placed.brain_ml, 1e-9);
  EXPECT_NEAR(physical.ventricles_ml * volume_scale, as_placed.ventricles_ml, 1e-9);

  // A brain that lost 8 % (a sinking without fluid found): as placed, the
  // reference's 7 % more made it -14 %, refused; in the preop's millilitres
  // it is -8 %, within brain shift's 10 %.
  const double lost = std::cbrt(0.92);
  const LabelImage sunk = head(lost, true);
  const auto check = [&](const CarriedPreopVolumes& reference) {
    return check_segmentation(sunk, ImageF(sunk.grid, 0.95f), reference, table(), AutoSegmentationParameters{}, 0.0);
  };
  const auto placed = check(as_placed), own = check(physical);
  EXPECT_NE(placed.failure.find("volume"), std::string::npos) << placed.metrics.dump();
  EXPECT_TRUE(own.failure.empty()) << own.failure << own.metrics.dump();
  EXPECT_NEAR(own.metrics["brain_volume"]["change"].get<double>(), -0.08, 0.01);

  EXPECT_THROW(carried_preop_volumes(carried, table(), 0.0), ComputeError);
}

// A re-match refused leaves the first round's answer: a caution says so and
// why (the classifier's or a gate's refusal, or the stages' fallback); a
// re-match that stands, or a first round alone, gives none.
TEST(SegmentationRounds, ARefusedReMatchCautionsTheAnswerWithItsReason) {
  const nlohmann::json first = {{"seconds", 0.5}};
  const nlohmann::json kept = {{"seconds", 0.9}};
  const nlohmann::json by_gate = {{"kept", false}, {"refusal", "automatic segmentation: the brain's volume differs"}};
  const nlohmann::json by_stages = {{"kept", false}, {"refusal", ""}, {"fallback_reason", "the non-rigid field folds"}};
  EXPECT_EQ(refused_rematch_caution(nlohmann::json::array({first, kept})), "");
  EXPECT_EQ(refused_rematch_caution(nlohmann::json::array({first})), "");
  EXPECT_EQ(refused_rematch_caution(nlohmann::json::array()), "");
  const std::string gate = refused_rematch_caution(nlohmann::json::array({first, by_gate}));
  EXPECT_NE(gate.find("re-match's segmentation was refused (automatic segmentation: the brain's volume"),
            std::string::npos) << gate;
  const std::string stages = refused_rematch_caution(nlohmann::json::array({first, kept, by_stages}));
  EXPECT_NE(stages.find("(the non-rigid field folds)"), std::string::npos) << stages;
  EXPECT_NE(gate.find("rests on the first round's"), std::string::npos) << gate;
  EXPECT_NE(stages.find("rests on the round's before it"), std::string::npos) << stages;
}
