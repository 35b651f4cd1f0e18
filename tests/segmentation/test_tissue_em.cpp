// The classifier on known mixtures: the head the classifier tests share
// (classifier_head.h), whose prior is the truth moved by a few mm (the
// misregistration the classifier must see through). Labels, class means and
// the bias must come back. The open-fluid rule on the same head:
// test_open_fluid.cpp.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>

#include "core/errors.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "phantom/phantom_artefacts.h"
#include "segmentation/intraop_segmentation.h"
#include "registration/boundary_samples.h"
#include "segmentation/bias_field.h"
#include "segmentation/sharpening_bias.h"
#include "segmentation/tissue_em.h"
#include "misregistered_prior.h"
#include "classifier_head.h"
#include "synthetic_head.h"

using namespace brainshift;
using namespace brainshift::segmentation;
using namespace brainshift::segmentation::test_support;
// Brain Dice counts the ventricles as brain (the outline), as the
// pipeline's outer surface does.
using brainshift::test::outline_dice;

TEST(TissueEm, RecoversLabelsMeansAndBiasOfAKnownMixture) {
  const Intensities in;
  const Synthetic head = make_head(in, 5.0, 0.3);
  const LabelImage prior = misregistered(head.truth, {3, -2, 2}, 1.04);
  const IntraopSegmentation seg = segment_intraop(head.image, prior, 1, {2}, params_for_test());
  ASSERT_TRUE(seg.refusal.empty()) << seg.refusal;
  const double brain_dice = outline_dice(seg.labels, head.truth), vent_dice = dice(seg.labels, head.truth, 2);
  const double prior_dice = outline_dice(prior, head.truth);
  EXPECT_GE(brain_dice, 0.97) << seg.report.dump();
  EXPECT_GT(brain_dice, prior_dice) << "the image must correct the misregistered prior";
  EXPECT_GE(vent_dice, 0.85) << seg.report.dump();
  // The bias is known only up to a constant (it trades with the class means):
  // compare the ratio of the means and of the bias.
  const GaussianClass* wm = nearest_class(seg, Tissue::parenchyma, in.wm);
  const GaussianClass* gm = nearest_class(seg, Tissue::parenchyma, in.gm);
  const GaussianClass* csf = nearest_class(seg, Tissue::ventricle, in.ventricle);
  ASSERT_TRUE(wm && gm && csf);
  EXPECT_NEAR(gm->mean / wm->mean, in.gm / in.wm, 0.05) << seg.report.dump();
  EXPECT_NEAR(csf->mean / wm->mean, in.ventricle / in.wm, 0.05) << seg.report.dump();
  EXPECT_NEAR(wm->sd / wm->mean, 5.0 / in.wm, 0.03) << seg.report.dump();
  // Bias: after removing the level, the fitted and the true log bias agree
  // inside the brain to a small fraction of the bias' own range (+-0.3).
  double mean_diff = 0;
  std::size_t n = 0;
  for (std::size_t v = 0; v < seg.bias.voxels.size(); ++v)
    if (head.truth.voxels[v]) {
      mean_diff += std::log(seg.bias.voxels[v]) - std::log(head.true_bias.voxels[v]);
      ++n;
    }
  mean_diff /= static_cast<double>(n);
  double rms = 0;
  for (std::size_t v = 0; v < seg.bias.voxels.size(); ++v)
    if (head.truth.voxels[v]) {
      const double d = std::log(seg.bias.voxels[v]) - std::log(head.true_bias.voxels[v]) - mean_diff;
      rms += d * d;
    }
  rms = std::sqrt(rms / static_cast<double>(n));
  EXPECT_LT(rms, 0.03) << "log-bias rms error";
  // Confidence is a probability and high in most of the brain.
  std::size_t confident = 0;
  for (std::size_t v = 0; v < seg.confidence.voxels.size(); ++v) {
    ASSERT_GE(seg.confidence.voxels[v], 0.f);
    ASSERT_LE(seg.confidence.voxels[v], 1.0001f);
    if (head.truth.voxels[v] && seg.confidence.voxels[v] > 0.9f) ++confident;
  }
  EXPECT_GT(static_cast<double>(confident) / static_cast<double>(n), 0.8);
}

TEST(TissueEm, BrightFluidContrastIsFittedFromThePriorNotFromAnOrdering) {
  Intensities t2;
  t2.wm = 55;
  t2.gm = 75;
  t2.ventricle = 150;
  t2.fluid = 150;
  t2.skull = 8;
  t2.scalp = 90;
  t2.air = 2;
  const Synthetic head = make_head(t2, 5.0, 0.2);
  const LabelImage prior = misregistered(head.truth, {-2, 2, 1}, 0.97);
  const IntraopSegmentation seg = segment_intraop(head.image, prior, 1, {2}, params_for_test());
  ASSERT_TRUE(seg.refusal.empty()) << seg.refusal;
  std::printf("T2-like head: outline Dice %.4f\n", outline_dice(seg.labels, head.truth));
  EXPECT_GE(outline_dice(seg.labels, head.truth), 0.95) << seg.report.dump();
  EXPECT_GE(dice(seg.labels, head.truth, 2), 0.85) << seg.report.dump();
}

// Where the brain's tissue is of one intensity (grey and white matter close,
// as on a FLAIR-like image) and the prior's brain holds fluid (sulci, a
// sinking's gap), a second parenchyma class fits that fluid and would hold
// it as brain: the fit gives it up, and no parenchyma class sits on the
// fluid. A slab image: brain tissue (55) with a fifth of fluid (12) where
// the prior says brain, ventricular fluid where it says ventricle, bone and
// air outside.
TEST(TissueEm, AParenchymaClassOnTheFluidIsGivenUp) {
  Grid3 g;
  g.dims = {60, 60, 40};
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  ImageF image(g, 0.f);
  TissuePrior prior;
  prior.grid = g;
  for (auto& p : prior.p) p.assign(g.voxel_count(), 0.f);
  std::mt19937_64 rng(11);
  std::normal_distribution<float> noise(0.f, 4.f);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        float value;
        int tissue;
        if (i < 10) {
          value = (j + k) % 2 ? 2.f : 10.f;  // air and bone
          tissue = 2;
        } else if (i < 16) {
          value = 12.f;  // the ventricles' fluid
          tissue = 1;
        } else {
          value = (i * 7 + j * 3 + k) % 5 == 0 ? 12.f : 55.f;  // tissue with a fifth of fluid
          tissue = 0;
        }
        image.voxels[v] = std::max(0.f, value + noise(rng));
        for (int t = 0; t < kTissues; ++t) prior.p[t][v] = t == tissue ? 0.98f : 0.01f;
      }
  prior.ventricle_share = 0.1;
  EmParameters params;
  params.fit_samples = 20000;
  const EmResult em = fit_tissue_mixture(image, prior, params);
  const GaussianClass* fluid = heaviest_class(em.classes, Tissue::ventricle);
  ASSERT_TRUE(fluid);
  int parenchyma = 0;
  for (const auto& c : em.classes)
    if (c.tissue == Tissue::parenchyma) {
      ++parenchyma;
      EXPECT_GT(c.mean - fluid->mean, fluid->sd) << "a parenchyma class on the fluid: " << c.mean << " +- " << c.sd;
    }
  EXPECT_EQ(em.parenchyma_classes_dropped, 1);
  EXPECT_EQ(parenchyma, 1);
}

TEST(TissueEm, ACavityOfFluidWhereThePriorHasBrainBecomesBackground) {
  const Intensities in;
  const Synthetic head = make_head(in, 5.0, 0.2, 12.0);
  // The prior is the head before the resection.
  const Synthetic before = make_head(in, 5.0, 0.2, 0.0);
  const IntraopSegmentation seg = segment_intraop(head.image, before.truth, 1, {2}, params_for_test());
  ASSERT_TRUE(seg.refusal.empty()) << seg.refusal;
  std::size_t cavity = 0, labelled_zero = 0;
  for (std::size_t v = 0; v < head.truth.voxels.size(); ++v)
    if (before.truth.voxels[v] == 1 && head.truth.voxels[v] == 0) {
      ++cavity;
      labelled_zero += seg.labels.voxels[v] == 0;
    }
  ASSERT_GT(cavity, 1000u);
  EXPECT_GT(static_cast<double>(labelled_zero) / static_cast<double>(cavity), 0.9);
  EXPECT_GE(outline_dice(seg.labels, head.truth), 0.97) << seg.report.dump();
}


// Ventricles that moved farther than they are thick (the brain's deep shift
// after the head's alignment alone): where the carried ventricles were the
// image shows white matter. Their prior is an even chance within the shift
// margin, their class starts from the brain's fluid: they are found where
// they are now, in a T1-like and in a T2-like contrast.
TEST(TissueEm, VentriclesMovedFartherThanTheirThicknessAreFoundWhereTheyAre) {
  for (const bool bright_fluid : {false, true}) {
    Intensities in;
    if (bright_fluid) {
      in.wm = 55;
      in.gm = 75;
      in.ventricle = in.fluid = 150;
      in.scalp = 90;
    }
    const Synthetic head = make_head(in, 5.0, 0.2);
    // The prior: the truth's outline, its ventricles 7 mm higher (the
    // ventricle ellipsoids are 16 mm tall, their walls 6 mm from the midline).
    LabelImage prior = head.truth;
    for (auto& v : prior.voxels)
      if (v == 2) v = 1;
    const LabelImage moved = misregistered(head.truth, {0, 0, 11}, 1.0);
    for (std::size_t v = 0; v < prior.voxels.size(); ++v)
      if (moved.voxels[v] == 2 && prior.voxels[v] != 0) prior.voxels[v] = 2;
    ASSERT_LT(dice(prior, head.truth, 2), 0.6) << "the prior's ventricles must be mostly wrong";
    SegmentationParameters p = params_for_test();
    p.ventricle_shift_mm = 11.0;
    const IntraopSegmentation seg = segment_intraop(head.image, prior, 1, {2}, p);
    ASSERT_TRUE(seg.refusal.empty()) << seg.refusal;
    EXPECT_GE(dice(seg.labels, head.truth, 2), 0.85) << (bright_fluid ? "T2-like " : "T1-like ") << seg.report.dump();
    EXPECT_GE(outline_dice(seg.labels, head.truth), 0.97) << seg.report.dump();
  }
}

// A regular subsample must see the whole image whatever its row length: a
// grid-order stride sharing a factor with it sees a few planes only.
TEST(TissueEm, TheFitSeesTheWholeImageWhateverTheGridDimensions) {
  const Intensities in;
  // 0.85 mm in plane: 200 voxels a row; the old stride for 60000 samples was
  // 200 * 223 * 75 / 60000 = 55 (odd, kept), 5 * 11, sharing 5 with 200.
  const Synthetic head = make_head(in, 5.0, 0.0, 0.0, {0.85, 0.85, 2.0});
  const IntraopSegmentation seg = segment_intraop(head.image, head.truth, 1, {2}, params_for_test());
  ASSERT_TRUE(seg.refusal.empty()) << seg.refusal;
  const GaussianClass* csf = nearest_class(seg, Tissue::ventricle, in.ventricle);
  ASSERT_TRUE(csf);
  EXPECT_NEAR(csf->mean, in.ventricle, 5.0) << seg.report.dump();
  EXPECT_GE(dice(seg.labels, head.truth, 2), 0.85) << seg.report.dump();
}

// The fit's time is in proportion to its samples: at most the budget on any
// grid. On 2 x 2 x 2.5 mm (the first round's prior grid) strides rounded per
// axis took a third more; on 1.45 mm they would take all voxels.
TEST(TissueEm, TheFitTakesAtMostItsSampleBudgetOnAnyGrid) {
  const Intensities in;
  for (const Eigen::Vector3d& spacing : {Eigen::Vector3d(2.0, 2.0, 2.5), Eigen::Vector3d(1.45, 1.45, 1.45)}) {
    const Synthetic head = make_head(in, 5.0, 0.0, 0.0, spacing);
    SegmentationParameters params = params_for_test();
    params.em.fit_samples = 20000;
    const IntraopSegmentation seg = segment_intraop(head.image, head.truth, 1, {2}, params);
    ASSERT_TRUE(seg.refusal.empty()) << seg.refusal;
    const auto samples = seg.report.at("samples").get<std::size_t>();
    EXPECT_LE(samples, params.em.fit_samples) << spacing.transpose();
    EXPECT_GE(samples, params.em.fit_samples / 3) << spacing.transpose();
  }
}

TEST(TissueEm, AnImageThatCannotShowTheVentriclesIsRefusedWithTheReason) {
  Intensities flat;
  flat.ventricle = flat.wm;  // no fluid/tissue contrast at all
  const Synthetic head = make_head(flat, 5.0, 0.1);
  const IntraopSegmentation seg = segment_intraop(head.image, head.truth, 1, {2}, params_for_test());
  EXPECT_NE(seg.refusal.find("ventricular fluid"), std::string::npos) << seg.report.dump();
}

TEST(TissueEm, BadInputIsAnInputError) {
  const Synthetic head = make_head(Intensities{}, 5.0, 0.0);
  LabelImage empty(head.truth.grid, 0);
  EXPECT_THROW(segment_intraop(head.image, empty, 1, {2}, params_for_test()), std::exception);
  Grid3 other = head.truth.grid;
  other.dims[0] -= 1;
  EXPECT_THROW(segment_intraop(ImageF(other, 1.f), head.truth, 1, {2}, params_for_test()), std::exception);
  EXPECT_THROW(LogBiasField(head.truth.grid, 7), std::exception);
}

TEST(TissuePrior, ReachIsWhereTheOutlinesPriorMeetsTheFloor) {
  Grid3 g;
  g.dims = {48, 6, 6};
  g.world_from_voxel = Eigen::Matrix4d::Identity();  // 1 mm voxels
  Mask outline(g, 0), ventricles(g, 0);
  for (int k = 0; k < 6; ++k)
    for (int j = 0; j < 6; ++j)
      for (int i = 0; i < 8; ++i) outline.at(i, j, k) = 1;
  ventricles.at(2, 3, 3) = 1;
  const double floor = 1e-3;
  PriorWidths w;
  w.outline_mm = 3.0;
  const double reach = prior_reach_mm(w.outline_mm, floor);
  EXPECT_NEAR(reach, 3.0 * std::log(997.0), 1e-12);
  const TissuePrior prior = tissue_prior(outline, ventricles, w, floor);
  // The parenchyma's prior is the floor plus the logistic's share: that
  // share equals the floor at the reach, more nearer, less beyond.
  for (int i = 8; i < 48; ++i) {
    const double beyond_mm = i - 7.5;  // from the outline's face, between voxel centres
    const double p = prior.p[0][g.index(i, 3, 3)];
    if (beyond_mm < reach - 1.0) {
      EXPECT_GT(p, 2 * floor) << i;
    } else if (beyond_mm > reach + 1.0) {
      EXPECT_LT(p, 2 * floor) << i;
    }
  }
  EXPECT_THROW(prior_reach_mm(0.0, floor), std::exception);
  EXPECT_THROW(prior_reach_mm(1.0, 0.0), std::exception);
}

// The fit's own classes and bias, given back under the same prior, give the
// fit's posterior: classify_with_classes is the fit's last step alone.
TEST(TissueEm, ClassifyingWithTheFittedClassesReproducesTheFitsPosterior) {
  const Synthetic head = make_head(Intensities{}, 5.0, 0.3);
  const LabelImage carried = misregistered(head.truth, {2, -1, 1}, 1.02);
  const TissuePrior prior = tissue_prior(outline_mask(carried), mask_of_labels(carried, {2}), PriorWidths{}, 1e-3);
  const EmParameters params;
  const EmResult fit = fit_tissue_mixture(head.image, prior, params);
  ASSERT_TRUE(fit.bias_field.has_value());
  std::vector<float> log_bias(fit.bias.size());
  for (std::size_t v = 0; v < log_bias.size(); ++v) log_bias[v] = std::log(fit.bias[v]);
  const EmResult again = classify_with_classes(head.image, prior, fit.classes, log_bias, params);
  EXPECT_EQ(again.iterations, 0);
  float worst = 0;
  for (int t = 0; t < kTissues; ++t)
    for (std::size_t v = 0; v < log_bias.size(); ++v)
      worst = std::max(worst, std::abs(again.posterior[t][v] - fit.posterior[t][v]));
  EXPECT_LT(worst, 1e-3f);
  EXPECT_THROW(classify_with_classes(head.image, prior, {}, log_bias, params), std::exception);
  EXPECT_THROW(classify_with_classes(head.image, prior, fit.classes, {1.f}, params), std::exception);
}

// The fitted log bias on another box of the same image (the re-match's):
// the same polynomial, extended beyond the grid it was fitted on.
TEST(BiasField, ABoxOffTheFittedGridIsThePolynomialThere) {
  Grid3 g;
  g.dims = {20, 16, 10};
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  LogBiasField field(g, 2);
  std::vector<std::array<int, 3>> voxels;
  std::vector<double> ratio, weight;
  for (int k = 0; k < 10; ++k)
    for (int j = 0; j < 16; ++j)
      for (int i = 0; i < 20; ++i) {
        voxels.push_back({i, j, k});
        ratio.push_back(0.02 * i - 0.001 * j * j + 0.01 * i * k / 10.0);
        weight.push_back(1.0);
      }
  ASSERT_TRUE(field.fit(voxels, ratio, weight));
  const std::array<int, 3> origin{-4, 3, 2}, dims{30, 9, 12};  // past the grid on two axes
  const std::vector<float> box = field.log_bias_box(origin, dims);
  ASSERT_EQ(box.size(), static_cast<std::size_t>(30 * 9 * 12));
  std::size_t n = 0;
  for (int k = 0; k < dims[2]; ++k)
    for (int j = 0; j < dims[1]; ++j)
      for (int i = 0; i < dims[0]; ++i, ++n)
        ASSERT_NEAR(box[n], field.log_bias(origin[0] + i, origin[1] + j, origin[2] + k), 1e-5) << i << " " << j << " " << k;
  const std::vector<float> whole = field.log_bias_image();
  EXPECT_NEAR(whole[g.index(7, 5, 3)], field.log_bias(7, 5, 3), 1e-5);
}

// A re-match (a narrower prior from a better estimate, a smaller box) with
// the first round's classes and bias: no EM fit, and the segmentation a refit
// gives, to within partial-volume voxels; the bias carried onto the smaller
// box is the first round's.
TEST(TissueEm, ARematchWithTheFirstRoundsFitAgreesWithARefit) {
  const Intensities in;
  const Synthetic head = make_head(in, 5.0, 0.3);
  // With the histogram's shading the earlier round's bias is carried as its
  // image, without it (the default) as its polynomial.
  for (const bool sharpening : {true, false}) {
  SCOPED_TRACE(sharpening ? "sharpening bias" : "polynomial bias only");
  SegmentationParameters first = params_for_test();
  first.sharpening_bias = sharpening;
  first.ventricle_shift_mm = 6.0;  // as the first image-only round: the ventricles' class held
  const IntraopSegmentation round1 =
      segment_intraop(head.image, misregistered(head.truth, {3, -2, 2}, 1.04), 1, {2}, first);
  ASSERT_TRUE(round1.refusal.empty()) << round1.refusal;
  ASSERT_EQ(round1.bias_field.has_value(), !sharpening);
  SegmentationParameters second = params_for_test();
  second.sharpening_bias = sharpening;
  second.prior_width_mm = 1.5;
  second.margin_mm = 10.4;
  const LabelImage carried = misregistered(head.truth, {1, -0.5, 0.5}, 1.01);
  const IntraopSegmentation reused = segment_intraop(head.image, carried, 1, {2}, second, &round1);
  const IntraopSegmentation refit = segment_intraop(head.image, carried, 1, {2}, second);
  ASSERT_TRUE(reused.refusal.empty()) << reused.refusal;
  ASSERT_TRUE(refit.refusal.empty()) << refit.refusal;
  EXPECT_EQ(reused.report["iterations"].get<int>(), 0);
  EXPECT_TRUE(reused.report["classes_from_earlier_round"].get<bool>());
  EXPECT_GT(refit.report["iterations"].get<int>(), 0);
  EXPECT_GE(outline_dice(reused.labels, refit.labels), 0.99);
  EXPECT_GE(outline_dice(reused.labels, head.truth), 0.97) << reused.report.dump();
  EXPECT_GE(dice(reused.labels, head.truth, 2), dice(refit.labels, head.truth, 2) - 0.02) << reused.report.dump();
  std::size_t compared = 0;
  for (std::size_t v = 0; v < reused.bias.voxels.size(); ++v) {
    if (reused.bias.voxels[v] == 1.f || round1.bias.voxels[v] == 1.f) continue;
    ++compared;
    ASSERT_NEAR(reused.bias.voxels[v] / round1.bias.voxels[v], 1.0, 1e-4) << v;
  }
  EXPECT_GT(compared, reused.bias.voxels.size() / 4);
  }
}

namespace {

// A receive array's shading on the test head, as the suites make it
// (phantom's coil_array_bias: 8 loops of radius 45 mm, 110 mm from the
// brain's centre, root-sum-of-squares, no intensity normalisation), as a
// log, mean 0 over the brain: bright under each loop, dark in the middle, no
// low-order polynomial.
ImageF array_shading(const Synthetic& head) {
  std::mt19937_64 rng(3);
  const std::vector<float> b = coil_array_bias(head.image.grid, Eigen::Vector3d::Zero(), 8, 110.0, 45.0, 60.0, 1.0, rng);
  ImageF log_b(head.image.grid, 0.f);
  double mean = 0;
  std::size_t n = 0;
  for (std::size_t v = 0; v < b.size(); ++v) {
    log_b.voxels[v] = std::log(b[v]);
    if (head.truth.voxels[v]) mean += log_b.voxels[v], ++n;
  }
  for (auto& v : log_b.voxels) v -= static_cast<float>(mean / static_cast<double>(n));
  return log_b;
}

// rms over the brain of (a - b) after their mean difference there.
double rms_over_brain(const std::vector<float>& a, const std::vector<float>& b, const LabelImage& truth) {
  double mean = 0, sum2 = 0;
  std::size_t n = 0;
  for (std::size_t v = 0; v < a.size(); ++v)
    if (truth.voxels[v]) mean += a[v] - b[v], ++n;
  mean /= static_cast<double>(n);
  for (std::size_t v = 0; v < a.size(); ++v)
    if (truth.voxels[v]) sum2 += (a[v] - b[v] - mean) * (a[v] - b[v] - mean);
  return std::sqrt(sum2 / static_cast<double>(n));
}

}  // namespace

// The histogram's sharpening finds an array's shading that no polynomial
// follows, and leaves an unshaded image nearly alone.
TEST(SharpeningBias, FindsAReceiveArraysShadingAndLeavesAnUnshadedImageAlone) {
  const Intensities in;
  Synthetic head = make_head(in, 3.0, 0.0);
  const Mask brain = nonzero_mask(head.truth);
  const std::vector<float> zero(head.image.voxels.size(), 0.f);
  const SharpeningBias unshaded = sharpening_log_bias(head.image, brain, {});
  ASSERT_EQ(unshaded.log_bias.size(), head.image.voxels.size());
  const double unshaded_rms = rms_over_brain(unshaded.log_bias, zero, head.truth);

  const ImageF log_b = array_shading(head);
  const double shading_rms = rms_over_brain(log_b.voxels, zero, head.truth);
  for (std::size_t v = 0; v < head.image.voxels.size(); ++v) head.image.voxels[v] *= std::exp(log_b.voxels[v]);
  const SharpeningBias shaded = sharpening_log_bias(head.image, brain, {});
  const double error_rms = rms_over_brain(shaded.log_bias, log_b.voxels, head.truth);
  std::printf("shading rms %.3f, error %.3f (%d iterations); unshaded field rms %.3f\n", shading_rms, error_rms,
              shaded.iterations, unshaded_rms);
  EXPECT_GT(shading_rms, 0.15) << "the test's shading must be strong";
  EXPECT_LT(error_rms, 0.2 * shading_rms);
  EXPECT_LT(unshaded_rms, 0.02);
  EXPECT_LE(shaded.iterations, SharpeningBiasParameters{}.max_iterations);
}

// The classes on an array-shaded head: the shading taken out first, the
// brain and ventricles come back as on an unshaded one.
TEST(SharpeningBias, TheClassifierSeesThroughAReceiveArraysShading) {
  const Intensities in;
  Synthetic head = make_head(in, 3.0, 0.0);
  const ImageF log_b = array_shading(head);
  for (std::size_t v = 0; v < head.image.voxels.size(); ++v) head.image.voxels[v] *= std::exp(log_b.voxels[v]);
  const LabelImage prior = misregistered(head.truth, {3, -2, 2}, 1.04);
  SegmentationParameters with = params_for_test(), without = params_for_test();
  with.sharpening_bias = true;
  without.sharpening_bias = false;
  const IntraopSegmentation seg = segment_intraop(head.image, prior, 1, {2}, with);
  const IntraopSegmentation plain = segment_intraop(head.image, prior, 1, {2}, without);
  ASSERT_TRUE(seg.refusal.empty()) << seg.refusal;
  const double with_dice = outline_dice(seg.labels, head.truth);
  const double without_dice = plain.refusal.empty() ? outline_dice(plain.labels, head.truth) : 0.0;
  std::printf("brain Dice %.4f with the sharpening, %.4f without (%s)\n", with_dice, without_dice,
              plain.refusal.empty() ? "accepted" : "refused");
  EXPECT_GE(with_dice, 0.97) << seg.report.dump();
  EXPECT_GT(with_dice, without_dice) << "the sharpening must help under the array";
  EXPECT_GE(dice(seg.labels, head.truth, 2), 0.85) << seg.report.dump();
  EXPECT_TRUE(seg.report.at("sharpening_bias").at("iterations").get<int>() > 0);
}

TEST(SharpeningBias, TooFewSamplesLeaveNoFieldAndBadInputIsAnError) {
  const Synthetic head = make_head(Intensities{}, 3.0, 0.0);
  Mask tiny(head.truth.grid, 0);
  tiny.at(70, 80, 37) = 1;
  const SharpeningBias none = sharpening_log_bias(head.image, tiny, {});
  EXPECT_EQ(none.iterations, 0);
  EXPECT_TRUE(std::all_of(none.log_bias.begin(), none.log_bias.end(), [](float v) { return v == 0.f; }));
  Grid3 other = head.truth.grid;
  other.dims[0] -= 1;
  EXPECT_THROW(sharpening_log_bias(head.image, Mask(other, 1), {}), InputError);
  // A field past what coils do is not used.
  Synthetic shaded = make_head(Intensities{}, 3.0, 0.0);
  const ImageF log_b = array_shading(shaded);
  for (std::size_t v = 0; v < shaded.image.voxels.size(); ++v) shaded.image.voxels[v] *= std::exp(log_b.voxels[v]);
  SharpeningBiasParameters strict;
  strict.max_log_bias = 0.1;
  const SharpeningBias past = sharpening_log_bias(shaded.image, nonzero_mask(shaded.truth), strict);
  EXPECT_TRUE(past.discarded);
  EXPECT_GT(past.max_abs_log_bias, 0.1);
  EXPECT_TRUE(std::all_of(past.log_bias.begin(), past.log_bias.end(), [](float v) { return v == 0.f; }));
  SharpeningBiasParameters bad;
  bad.smoothing_mm = 0;
  EXPECT_THROW(sharpening_log_bias(head.image, nonzero_mask(head.truth), bad), InputError);
}
