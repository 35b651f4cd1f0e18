// The image-only path's passes of the stages (pipeline/warm_state.h
// PassOptions, docs/DESIGN.md "Automatic intraop segmentation" item 9): a
// pass a re-match follows only makes the re-match's prior and runs light; the
// answer is always a full pass. On the small synthetic head (coarse mesh).
#include <gtest/gtest.h>
#include <mpi.h>

#include <cstring>
#include <optional>

#include "coarse_parameters.h"  // tests/support
#include "image/distance_map.h"
#include "image/morphology.h"
#include "pipeline/engine_session.h"
#include "pipeline/warm_state.h"
#include "pipeline/working_grid.h"
#include "synthetic_head.h"

using namespace brainshift;

namespace {

// The synthetic head on an iMRI-like grid (1.4 x 1.4 x 2.8 mm), moved by a
// translation; with sink_mm > 0 the top of the brain is cut away over a
// 30 mm disc (a sinking under a craniotomy), so the non-rigid stages work.
IntraopInput moved_scan(const PreopInput& preop, const Eigen::Vector3d& shift_mm, double sink_mm) {
  Grid3 g;
  g.dims = {100, 110, 44};
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  g.world_from_voxel.diagonal().head<3>() = Eigen::Vector3d(1.4, 1.4, 2.8);
  g.world_from_voxel.block<3, 1>(0, 3) = Eigen::Vector3d(-70, -77, -62);
  test::MovedHead moved = test::move_head(preop.labels, preop.t1, g, shift_mm);
  IntraopInput scan{std::move(moved.labels), std::move(moved.t1)};
  if (sink_mm > 0) test::sink_top(scan.labels, sink_mm, 30.0);
  return scan;
}

// moved_scan's extent at half its spacing: 0.7 x 0.7 x 1.4 mm.
Grid3 fine_grid() {
  Grid3 fine;
  fine.dims = {200, 220, 88};
  fine.world_from_voxel.diagonal().head<3>() = Eigen::Vector3d(0.7, 0.7, 1.4);
  fine.world_from_voxel.block<3, 1>(0, 3) = Eigen::Vector3d(-70.35, -77.35, -62.7);
  return fine;
}

// Mean error of a recovered translation over the labelled voxels (the
// pull-back field should be -shift everywhere).
double mean_translation_error(const ScanResult& r, const LabelImage& truth, const Eigen::Vector3d& shift) {
  double sum = 0;
  std::size_t n = 0;
  for (std::size_t v = 0; v < truth.voxels.size(); ++v)
    if (truth.voxels[v] != 0) sum += (r.pullback_field_mm.vectors[v].cast<double>() + shift).norm(), ++n;
  return sum / static_cast<double>(n);
}

class ImageOnlyPasses : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    test::SyntheticHead h = test::synthetic_head();
    preop_ = new PreopInput{std::move(h.t1), std::move(h.labels)};
  }
  static void TearDownTestSuite() { delete preop_; }
  static PreopInput* preop_;
};
PreopInput* ImageOnlyPasses::preop_ = nullptr;

TEST_F(ImageOnlyPasses, APriorOnlyPassCarriesTheSameLabelsWithoutTheAnswersOutputs) {
  PipelineParameters p = test::coarse_parameters();
  // Without the shortcuts the prior-only pass computes the same field.
  p.auto_segmentation.passes.prior_refine = true;
  p.auto_segmentation.passes.prior_surface_max_iterations = 0;
  auto warm = build_warm_state(MPI_COMM_WORLD, *preop_, p, nullptr, std::nullopt);
  ASSERT_FALSE(warm->models.empty());
  const IntraopInput scan = moved_scan(*preop_, {1.0, -1.0, 0.5}, 6.0);
  const ScanResult full = run_intraop(*warm, scan, p, nullptr, false);
  const ScanResult light = run_intraop(*warm, scan, p, nullptr, false, "", PassOptions{true});
  ASSERT_EQ(full.kind, ResultKind::nonrigid) << full.fallback_reason;
  ASSERT_EQ(light.kind, ResultKind::nonrigid) << light.fallback_reason;
  const auto& a = full.pullback_field_mm.vectors;
  const auto& b = light.pullback_field_mm.vectors;
  ASSERT_EQ(a.size(), b.size());
  EXPECT_EQ(std::memcmp(a.data(), b.data(), a.size() * sizeof(a[0])), 0) << "not the same field";
  EXPECT_EQ(light.warped_labels.voxels, full.warped_labels.voxels);
  EXPECT_FALSE(full.warped_t1.voxels.empty());
  EXPECT_TRUE(light.warped_t1.voxels.empty()) << "no warped T1 for a prior";
  EXPECT_EQ(full.models.size(), warm->models.size());
  EXPECT_TRUE(light.models.empty()) << "no models for a prior";
  EXPECT_FALSE(full.metrics.contains("pass"));
  EXPECT_TRUE(light.metrics.contains("pass"));
  // Made the answer, the light pass gets what it skipped: the full pass's outputs.
  ScanResult completed = light;
  complete_prior_pass(*warm, completed, nullptr);
  EXPECT_FALSE(completed.metrics.contains("pass"));
  EXPECT_EQ(completed.warped_t1.voxels, full.warped_t1.voxels);
  ASSERT_EQ(completed.models.size(), full.models.size());
  for (const auto& [name, model] : full.models)
    EXPECT_EQ(completed.models.at(name).vertices_mm, model.vertices_mm) << name;

  // With the shortcuts: the refinement skipped and said so, the membrane
  // stopped early at each stiffness level.
  p.auto_segmentation.passes.prior_refine = false;
  p.auto_segmentation.passes.prior_surface_max_iterations = 1;
  const ScanResult shortcut = run_intraop(*warm, scan, p, nullptr, false, "", PassOptions{true});
  ASSERT_EQ(shortcut.kind, ResultKind::nonrigid) << shortcut.fallback_reason;
  EXPECT_EQ(shortcut.metrics["refine"]["applied"], false);
  EXPECT_EQ(full.metrics["refine"]["applied"], true);
  const int levels = p.outer_surface.stiffness_levels;
  // One iteration per level; a full match needs convergence_iterations (2)
  // quiet ones at each level at least.
  EXPECT_EQ(shortcut.metrics["surfaces"]["outer"]["iterations"].get<int>(), levels);
  EXPECT_GE(full.metrics["surfaces"]["outer"]["iterations"].get<int>(), 2 * levels);
  EXPECT_FALSE(shortcut.warped_labels.voxels.empty());
}

TEST_F(ImageOnlyPasses, TheAnswerOfAnImageOnlyScanIsAFullPassWarmStartedFromTheLightOne) {
  EngineSession session(MPI_COMM_WORLD, test::coarse_parameters());
  session.load_preop(*preop_, nullptr);
  const Eigen::Vector3d shift(3.0, -2.0, 2.0);
  ScanInput scan;
  scan.image = test::scanner_image(*moved_scan(*preop_, shift, 0.0).t1);
  const ScanResult r = session.register_scan(scan, nullptr);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason << "\n" << r.metrics["segmentation"].dump();
  const auto& rounds = r.metrics["segmentation"]["rounds"];
  ASSERT_EQ(rounds.size(), 2u) << rounds.dump();
  for (const auto& round : rounds) EXPECT_FALSE(round.contains("kept")) << round.dump();
  // The first round's prior is the head placement's, wide and wider inside;
  // the re-match's the non-rigid estimate's, narrow (each width its own
  // parameter).
  const AutoSegmentationParameters ap = test::coarse_parameters().auto_segmentation;
  EXPECT_DOUBLE_EQ(rounds[0]["prior_width_mm"].get<double>(), ap.prior_width_affine_mm);
  EXPECT_DOUBLE_EQ(rounds[0]["prior_inward_width_mm"].get<double>(), ap.prior_inward_width_affine_mm);
  EXPECT_DOUBLE_EQ(rounds[1]["prior_width_mm"].get<double>(), ap.prior_width_nonrigid_mm);
  EXPECT_DOUBLE_EQ(rounds[1]["prior_inward_width_mm"].get<double>(), ap.prior_inward_width_nonrigid_mm);
  // A T1-like image: every round fits the classifier's bias degree (and
  // would with bright_fluid_bias_degree_affine set).
  const int degree = test::coarse_parameters().auto_segmentation.classifier.em.bias_degree;
  for (const auto& round : rounds) {
    EXPECT_EQ(round["bias_degree"], degree) << rounds.dump();
    EXPECT_FALSE(round.contains("bias_refitted")) << rounds.dump();
  }
  EXPECT_FALSE(r.metrics.contains("pass")) << "the answer is not a prior-only pass";
  EXPECT_FALSE(r.warped_t1.voxels.empty());
  EXPECT_FALSE(r.models.empty());
  EXPECT_EQ(r.metrics["affine"]["warm_start"], true);
  const auto& t = r.timings["intraop"];
  EXPECT_GT(t["earlier_passes"].get<double>(), 0.0);
  EXPECT_GE(t["total"].get<double>(), t["segment"].get<double>() + t["earlier_passes"].get<double>());
  // The recovered translation, from the image alone, as with one full pass.
  EXPECT_LT(mean_translation_error(r, moved_scan(*preop_, shift, 0.0).labels, shift), 0.5);

  // Without a re-match the only pass is the answer: full, from the full search.
  PipelineParameters one_round = test::coarse_parameters();
  one_round.auto_segmentation.rematch_rounds = 0;
  EngineSession single(MPI_COMM_WORLD, one_round);
  single.load_preop(*preop_, nullptr, session.mesh());
  const ScanResult s = single.register_scan(scan, nullptr);
  ASSERT_EQ(s.kind, ResultKind::nonrigid) << s.fallback_reason;
  EXPECT_FALSE(s.metrics.contains("pass"));
  EXPECT_EQ(s.metrics["affine"]["warm_start"], false);
  EXPECT_FALSE(s.warped_t1.voxels.empty());
}

// A bright-fluid (T2-like) image with bright_fluid_bias_degree_affine set
// to 1 (off by default): the first round, under the head placement's wide
// prior, fits its bias again, linear; the re-match at the classifier's
// degree; the translation is recovered as from a T1.
TEST_F(ImageOnlyPasses, ABrightFluidImagesFirstRoundFitsALinearBiasWhenAsked) {
  PipelineParameters p = test::coarse_parameters();
  p.auto_segmentation.bright_fluid_bias_degree_affine = 1;
  ASSERT_LT(p.auto_segmentation.bright_fluid_bias_degree_affine, p.auto_segmentation.classifier.em.bias_degree);
  EngineSession session(MPI_COMM_WORLD, p);
  session.load_preop(*preop_, nullptr);
  const Eigen::Vector3d shift(3.0, -2.0, 2.0);
  const IntraopInput moved = moved_scan(*preop_, shift, 0.0);
  ImageF t2 = *moved.t1;  // outside 10, ventricles 30, brain 100 (synthetic_head.h)
  for (std::size_t v = 0; v < t2.voxels.size(); ++v) {
    const std::uint16_t l = moved.labels.voxels[v];
    if (l == 2) t2.voxels[v] = 110.f;
    else if (l != 0) t2.voxels[v] = 50.f;
  }
  ScanInput scan;
  scan.image = test::scanner_image(t2);
  const ScanResult r = session.register_scan(scan, nullptr);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason << "\n" << r.metrics["segmentation"].dump();
  const auto& rounds = r.metrics["segmentation"]["rounds"];
  ASSERT_EQ(rounds.size(), 2u) << rounds.dump();
  EXPECT_EQ(rounds[0]["bias_degree"], p.auto_segmentation.bright_fluid_bias_degree_affine) << rounds.dump();
  EXPECT_TRUE(rounds[0].contains("bias_refitted")) << rounds.dump();
  EXPECT_EQ(rounds[1]["bias_degree"], p.auto_segmentation.classifier.em.bias_degree) << rounds.dump();
  EXPECT_FALSE(rounds[1].contains("bias_refitted")) << rounds.dump();
  EXPECT_LT(mean_translation_error(r, moved.labels, shift), 0.5);
  ASSERT_TRUE(r.intraop_labels);
  EXPECT_GT(test::outline_dice(*r.intraop_labels, moved.labels), 0.95);
}

// The synthetic head's T1 has no scalp, as a brain-extracted preop T1 (a
// planning system's, mricron-data's ch2bet): a scan that shows a scalp
// round the brain (bright, 5-10 mm out) is placed by intensity
// (registration/intensity_placement.h), not by matching the preop's brain
// to the scan's head, which would shrink it onto the scalp.
TEST_F(ImageOnlyPasses, ABrainExtractedPreopIsPlacedOnAScanWithAScalpByIntensity) {
  EngineSession session(MPI_COMM_WORLD, test::coarse_parameters());
  session.load_preop(*preop_, nullptr);
  const Eigen::Vector3d shift(3.0, -2.0, 2.0);
  const IntraopInput moved = moved_scan(*preop_, shift, 0.0);
  ImageF with_scalp = *moved.t1;
  const ImageF out_mm = distance_to_mask_mm(nonzero_mask(moved.labels));
  for (std::size_t v = 0; v < with_scalp.voxels.size(); ++v)
    if (out_mm.voxels[v] >= 5.f && out_mm.voxels[v] < 10.f) with_scalp.voxels[v] = 80.f;
  ScanInput scan;
  scan.image = test::scanner_image(with_scalp);
  const ScanResult r = session.register_scan(scan, nullptr);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason;
  const auto& placement = r.metrics["segmentation"]["head_placement"];
  EXPECT_EQ(placement.value("by", ""), "intensity") << placement.dump();
  EXPECT_GT(placement.value("correlation", 0.0), 0.7) << placement.dump();
  // 0.54 mm measured (0.3-0.45 without a scalp in the other tests here);
  // placed by the head outlines the scan was refused.
  EXPECT_LT(mean_translation_error(r, moved.labels, shift), 0.75);
  ASSERT_TRUE(r.intraop_labels);
  EXPECT_GT(test::outline_dice(*r.intraop_labels, moved.labels), 0.95);
}

// The first round, which only makes the re-match's prior, is worked on the
// coarser prior grid (PassShortcuts::prior_spacing_mm): 2 mm in-plane for
// this 1.4 x 1.4 x 2.8 mm scan, its slices left as they are; the re-match and
// the answer on the scan's own grid. A first round refused on the prior grid
// is decided again on the scan's own grid.
TEST_F(ImageOnlyPasses, TheFirstRoundIsWorkedOnTheCoarserPriorGridTheAnswerOnTheScans) {
  PipelineParameters p = test::coarse_parameters();
  p.auto_segmentation.passes.prior_spacing_mm = 2.0;
  EngineSession session(MPI_COMM_WORLD, p);
  session.load_preop(*preop_, nullptr);
  const Eigen::Vector3d shift(3.0, -2.0, 2.0);
  const IntraopInput moved = moved_scan(*preop_, shift, 0.0);
  ScanInput scan;
  scan.image = test::scanner_image(*moved.t1);
  const ScanResult r = session.register_scan(scan, nullptr);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason << "\n" << r.metrics["segmentation"].dump();
  const auto& prior = r.metrics["segmentation"]["prior_grid"];
  EXPECT_EQ(prior["dims"], nlohmann::json::array({70, 77, 44})) << prior.dump();
  EXPECT_FALSE(prior.contains("refused")) << prior.dump();
  const auto& rounds = r.metrics["segmentation"]["rounds"];
  ASSERT_EQ(rounds.size(), 2u) << rounds.dump();
  for (const auto& round : rounds) EXPECT_FALSE(round.contains("kept")) << round.dump();
  ASSERT_TRUE(r.intraop_labels);
  for (const Grid3* g : {&r.intraop_labels->grid, &r.pullback_field_mm.grid, &r.warped_labels.grid, &r.warped_t1.grid})
    EXPECT_TRUE(g->same_geometry(moved.labels.grid));
  EXPECT_FALSE(r.metrics.contains("working_grid")) << "answered on the scan's own grid";
  EXPECT_LT(mean_translation_error(r, moved.labels, shift), 0.5);
  EXPECT_GT(test::outline_dice(*r.intraop_labels, moved.labels), 0.95);

  // A gate no segmentation meets: refused on the prior grid, then on the
  // scan's own grid, for the same reason.
  PipelineParameters strict = p;
  strict.auto_segmentation.max_brain_volume_change = 1e-6;
  EngineSession strict_session(MPI_COMM_WORLD, strict);
  strict_session.load_preop(*preop_, nullptr, session.mesh());
  const ScanResult refused = strict_session.register_scan(scan, nullptr);
  EXPECT_EQ(refused.kind, ResultKind::affine_only_fallback);
  const auto& refused_prior = refused.metrics["segmentation"]["prior_grid"];
  ASSERT_TRUE(refused_prior.contains("refused")) << refused_prior.dump();
  EXPECT_NE(refused_prior["refused"].get<std::string>().find("the gates: automatic segmentation: the brain's volume"),
            std::string::npos) << refused_prior.dump();
  EXPECT_NE(refused.fallback_reason.find("the brain's volume"), std::string::npos) << refused.fallback_reason;
  ASSERT_TRUE(refused.intraop_labels);
  EXPECT_TRUE(refused.intraop_labels->grid.same_geometry(moved.labels.grid));
  // That gate judged the segmentation's outline, which the affine was fitted
  // to: the fallback delivers the affine's rigid part (a head does not shrink
  // or swell; docs/DESIGN.md "Quality gates"), the refused affine reported.
  EXPECT_EQ(refused.metrics["affine"].value("fallback_transform", ""),
            "rigid part of the affine (the automatic segmentation's brain volume was refused)")
      << refused.metrics["affine"].dump();
  EXPECT_TRUE(refused.metrics["affine"].contains("refused_intraop_from_preop"));
  const Eigen::Matrix3d rotation = refused.intraop_from_preop.topLeftCorner<3, 3>();
  EXPECT_LT((rotation.transpose() * rotation - Eigen::Matrix3d::Identity()).norm(), 1e-9);
  EXPECT_NEAR(rotation.determinant(), 1.0, 1e-9);
  EXPECT_LT(mean_translation_error(refused, moved.labels, shift), 0.5) << "the head's shift is kept";
}

// The answer's stages on the coarser stage grid
// (PassShortcuts::stage_spacing_mm, 2 mm by default; 0 turns it off), the
// segmentation on the scan's own grid: both rounds' segmentations and every
// output on the scan's grid, the stages' grid reported only when used, the
// translation recovered either way.
TEST_F(ImageOnlyPasses, TheAnswersStagesAreWorkedOnTheStageGridTheSegmentationOnTheScans) {
  const Eigen::Vector3d shift(3.0, -2.0, 2.0);
  const IntraopInput moved = moved_scan(*preop_, shift, 0.0);
  ScanInput scan;
  scan.image = test::scanner_image(*moved.t1);
  std::optional<TetMesh> mesh;
  for (const double spacing_mm : {2.0, 0.0}) {
    SCOPED_TRACE(spacing_mm);
    PipelineParameters p = test::coarse_parameters();
    p.auto_segmentation.passes.stage_spacing_mm = spacing_mm;
    EngineSession session(MPI_COMM_WORLD, p);
    session.load_preop(*preop_, nullptr, mesh);
    if (!mesh) mesh = session.mesh();
    const ScanResult r = session.register_scan(scan, nullptr);
    ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason << "\n" << r.metrics["segmentation"].dump();
    EXPECT_EQ(r.metrics.contains("stage_grid"), spacing_mm > 0) << r.metrics.dump();
    EXPECT_EQ(r.timings["intraop"].contains("stage_grid"), spacing_mm > 0);
    if (spacing_mm > 0) {
      EXPECT_EQ(r.metrics["stage_grid"]["dims"], nlohmann::json::array({70, 77, 44}));
      // The fold gate judged the stage grid's field; the delivered one is measured too.
      EXPECT_GT(r.metrics["jacobian"]["delivered_min"].get<double>(), 0.5) << r.metrics["jacobian"].dump();
      EXPECT_EQ(r.metrics["jacobian"]["delivered_folded_voxels"], 0);
    }
    EXPECT_EQ(r.metrics["jacobian"].contains("delivered_min"), spacing_mm > 0);
    EXPECT_EQ(r.metrics["segmentation"]["rounds"].size(), 2u);
    ASSERT_TRUE(r.intraop_labels && r.segmentation_confidence);
    for (const Grid3* g : {&r.intraop_labels->grid, &r.segmentation_confidence->grid, &r.pullback_field_mm.grid,
                           &r.warped_labels.grid, &r.warped_t1.grid})
      EXPECT_TRUE(g->same_geometry(moved.labels.grid));
    EXPECT_LT(mean_translation_error(r, moved.labels, shift), 0.5);
    EXPECT_GT(test::outline_dice(*r.intraop_labels, moved.labels), 0.95);
    EXPECT_GT(test::outline_dice(r.warped_labels, moved.labels), 0.95);
  }
}

// The working grid (pipeline/working_grid.h): only an axis much finer than
// the working spacing is coarsened, to whole voxels over the same extent.
TEST(WorkingGrid, OnlyAxesMuchFinerThanTheWorkingSpacingAreCoarsened) {
  const auto grid_of = [](std::array<int, 3> dims, Eigen::Vector3d spacing) {
    Grid3 g;
    g.dims = dims;
    g.world_from_voxel.diagonal().head<3>() = spacing;
    return g;
  };
  const Grid3 iso = grid_of({258, 309, 229}, {0.7, 0.7, 0.7});
  const Grid3 w = working_grid(iso, 1.0);
  EXPECT_EQ(w.dims, (std::array<int, 3>{181, 216, 160}));
  for (int a = 0; a < 3; ++a) EXPECT_NEAR(w.spacing_mm()[a], 1.0, 0.01);
  // As validated: a 1.5 T scan's 0.94 mm in-plane is worked on as it is.
  const Grid3 clinical = grid_of({256, 256, 60}, {0.9375, 0.9375, 2.5});
  EXPECT_EQ(working_grid(clinical, 1.0).dims, clinical.dims);
  // Fine in-plane, thick slices: only the plane.
  EXPECT_EQ(working_grid(grid_of({512, 512, 40}, {0.45, 0.45, 3.0}), 1.0).dims, (std::array<int, 3>{230, 230, 40}));
  EXPECT_EQ(working_grid(iso, 0.0).dims, iso.dims) << "0: off";
}

// A scan finer than the working grid is segmented and registered on the
// working grid and answered on its own, pushed as an image, as labels (a
// site's correction of the automatic segmentation of a 3 T scan is drawn on
// that scan's grid) or as both: every output on the scan's grid, the
// translation recovered as on the coarser scan
// (PipelineTest.AScanGivenAsAnImageAloneIsSegmentedAndRegistered).
TEST_F(ImageOnlyPasses, AFineScanIsWorkedOnTheWorkingGridAndAnsweredOnItsOwn) {
  EngineSession session(MPI_COMM_WORLD, test::coarse_parameters());
  session.load_preop(*preop_, nullptr);
  const Grid3 fine = fine_grid();
  const Eigen::Vector3d shift(3.0, -2.0, 2.0);
  const test::MovedHead truth = test::move_head(preop_->labels, preop_->t1, fine, shift);
  enum class Pushed { image, labels, both };
  for (const Pushed pushed : {Pushed::image, Pushed::labels, Pushed::both}) {
    SCOPED_TRACE(static_cast<int>(pushed));
    ScanInput scan;
    if (pushed != Pushed::labels) scan.image = test::scanner_image(truth.t1);
    if (pushed != Pushed::image) scan.labels = truth.labels;
    const ScanResult r = session.register_scan(scan, nullptr);
    ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason << "\n" << r.metrics.dump();
    const auto& worked = r.metrics["working_grid"];
    EXPECT_EQ(worked["dims"], nlohmann::json::array({140, 154, 88})) << worked.dump();
    EXPECT_EQ(worked["image_dims"], nlohmann::json::array({200, 220, 88}));
    EXPECT_GT(r.timings["intraop"].value("working_grid", 0.0), 0.0);
    for (const Grid3* g : {&r.pullback_field_mm.grid, &r.warped_labels.grid, &r.warped_t1.grid,
                           &r.warped_t1_affine_only.grid}) {
      EXPECT_TRUE(g->same_geometry(fine));
    }
    EXPECT_LT(mean_translation_error(r, truth.labels, shift), 0.5);
    // The overlap figures judge the labels used, on the scan's grid.
    EXPECT_GT(r.metrics["labels"]["brain"]["dice"].get<double>(), 0.95) << r.metrics["labels"].dump();
    EXPECT_EQ(r.metrics.contains("label_image_check"), pushed == Pushed::both);
    // The engine's segmentation, when it made one: of the image alone, or of
    // the labels refined by their image (the default), on the working grid too.
    ASSERT_EQ(r.intraop_labels.has_value(), pushed != Pushed::labels) << r.metrics["given_labels"].dump();
    if (pushed == Pushed::both) {
      EXPECT_TRUE(r.metrics["given_labels"].value("refined", false));
    }
    if (pushed == Pushed::labels) continue;
    ASSERT_TRUE(r.segmentation_confidence);
    EXPECT_TRUE(r.intraop_labels->grid.same_geometry(fine));
    EXPECT_TRUE(r.segmentation_confidence->grid.same_geometry(fine));
    EXPECT_GT(test::outline_dice(*r.intraop_labels, truth.labels), 0.95);
  }
}

}  // namespace

namespace {

// The synthetic head with a cistern: a fluid space at the base of the brain,
// open to the CSF below it, that the preop labels count as brain (as atlas
// labels count the basal cisterns) though its T1 is the ventricles' fluid.
PreopInput head_with_cistern(const Eigen::Vector3d& centre_mm, double radius_mm) {
  test::SyntheticHead h = test::synthetic_head();
  const Grid3& g = h.labels.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        if (h.labels.at(i, j, k) == 1 && (g.world_mm(i, j, k) - centre_mm).norm() < radius_mm) h.t1.at(i, j, k) = 30;
  return PreopInput{std::move(h.t1), std::move(h.labels)};
}

}  // namespace

// A fluid space the preop labels call brain, which the classification of the
// intraop image leaves outside (dark, at the outline), is given back to the
// brain as for given labels (segmentation/preop_fluid_spaces.h): the outline
// is the preop's, so the field does not pull the preop's tissue into it.
TEST(ImageOnlyFluidSpaces, ACisternThePreopLabelsCallBrainIsGivenBackToTheSegmentation) {
  const Eigen::Vector3d cistern_mm(0, 15, -44);  // the ellipsoid's floor is at z = -48
  const double radius_mm = 9.0;
  const PreopInput preop = head_with_cistern(cistern_mm, radius_mm);
  EngineSession session(MPI_COMM_WORLD, test::coarse_parameters());
  session.load_preop(preop, nullptr);
  const Eigen::Vector3d shift(1.0, -1.0, 1.0);
  const IntraopInput truth = moved_scan(preop, shift, 0.0);
  ScanInput scan;
  scan.image = test::scanner_image(*truth.t1);
  const ScanResult r = session.register_scan(scan, nullptr);
  ASSERT_EQ(r.kind, ResultKind::nonrigid) << r.fallback_reason << "\n" << r.metrics["segmentation"].dump();
  // The cistern, moved with the head (dark and labelled brain in the
  // truth), is brain in the answer's labels.
  ASSERT_TRUE(r.intraop_labels);
  std::size_t cistern = 0, kept = 0;
  const Grid3& g = truth.labels.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        if (truth.labels.at(i, j, k) == 1 && (g.world_mm(i, j, k) - cistern_mm - shift).norm() < radius_mm - 1.5) {
          ++cistern;
          kept += r.intraop_labels->at(i, j, k) != 0;
        }
  ASSERT_GT(cistern, 100u);
  EXPECT_GT(static_cast<double>(kept) / static_cast<double>(cistern), 0.9) << kept << " of " << cistern;
  const auto& classifier = r.metrics["segmentation"]["classifier"];
  ASSERT_TRUE(classifier.contains("preop_fluid_spaces")) << classifier.dump();
  EXPECT_GT(classifier["preop_fluid_spaces"].value("added_ml", 0.0), 0.5) << classifier["preop_fluid_spaces"].dump();
  EXPECT_GT(test::outline_dice(*r.intraop_labels, truth.labels), 0.95);
  EXPECT_LT(mean_translation_error(r, truth.labels, shift), 0.5);
}
