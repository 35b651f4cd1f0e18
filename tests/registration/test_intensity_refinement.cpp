// The intensity refinement on a crop of the real Colin27 T1 (ch2): an
// iMRI-like oblique grid inside the brain, the "intraop" image made by
// deforming the T1 with a known smooth field, a multiplicative bias and
// Rician noise. Starting from u = 0 (as if the elastic model knew nothing of
// this motion), the refinement must recover most of the field; an identical
// pair must be left as it is; a T2-like contrast is followed through a
// transfer function; an unrelated image is not trusted.
#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <random>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "image/nifti_io.h"
#include "registration/intensity_refinement.h"
#include "registration/linear_sampler.h"
#include "synthetic.h"

namespace brainshift {
namespace {

const std::filesystem::path kT1 = "/usr/share/mricron/templates/ch2.nii.gz";
const std::filesystem::path kBrain = "/usr/share/mricron/templates/ch2bet.nii.gz";

// Two smooth bumps, at most ~2.7 mm: the kind of residual the elastic
// interior leaves, and well inside max_correction_mm.
Eigen::Vector3d true_pullback_mm(const Eigen::Vector3d& x, const Eigen::Vector3d& centre) {
  auto bump = [&](const Eigen::Vector3d& offset, double sigma_mm, const Eigen::Vector3d& amplitude_mm) {
    return amplitude_mm * std::exp(-(x - centre - offset).squaredNorm() / (2 * sigma_mm * sigma_mm));
  };
  return bump({15, -10, 5}, 25, {2.0, -1.5, 1.0}) + bump({-20, 15, -10}, 28, {-1.5, 1.0, 2.0});
}

// A scanner's grid and what a voxel integrates: by default 80 x 80 x 36
// voxels of 1.2 x 1.2 x 2.5 mm sampled at their centres; the corners reach
// past the brain surface.
struct Scanner {
  std::array<int, 3> dims{80, 80, 36};
  Eigen::Vector3d spacing_mm{1.2, 1.2, 2.5};
  // A voxel averages the scene over its box in-plane and a Gaussian slice
  // profile (FWHM one slice) across, as a low-field 2D acquisition.
  bool partial_volume = false;
};

struct Crop {
  ImageF intraop_t1;
  LabelImage labels;
  ImageF brain_sdf_mm;
  VectorImage3 truth_mm;  // x + truth(x) = preop point
};

class IntensityRefinementTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!std::filesystem::exists(kT1) || !std::filesystem::exists(kBrain)) return;
    t1_ = new ImageF(read_scalar_image(kT1));
    brain_ = new ImageF(read_scalar_image(kBrain));
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    std::vector<float> tissue;
    const Grid3& g = brain_->grid;
    const LinearSampler t1(*t1_);
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          if (brain_->at(i, j, k) <= 0) continue;
          sum += g.world_mm(i, j, k);
          double value;
          if (t1.sample(g.world_mm(i, j, k), &value, nullptr)) tissue.push_back(static_cast<float>(value));
        }
    centre_ = sum / static_cast<double>(tissue.size());
    std::nth_element(tissue.begin(), tissue.begin() + tissue.size() * 99 / 100, tissue.end());
    p99_ = tissue[tissue.size() * 99 / 100];
    std::nth_element(tissue.begin(), tissue.begin() + tissue.size() / 2, tissue.end());
    median_ = tissue[tissue.size() / 2];
  }
  static void TearDownTestSuite() {
    delete t1_;
    delete brain_;
  }
  void SetUp() override {
    if (!t1_) GTEST_SKIP() << kT1 << " is not installed (Debian package mricron-data)";
  }

  // The value a voxel centred at x records (the preop T1 pulled back by u).
  static double voxel_value(const LinearSampler& t1, const Grid3& g, int i, int j, int k, bool deform,
                            bool partial_volume) {
    auto at = [&](const Eigen::Vector3d& x) {
      double value = 0;
      t1.sample(x + (deform ? true_pullback_mm(x, centre_) : Eigen::Vector3d::Zero()), &value, nullptr);
      return value;
    };
    if (!partial_volume) return at(g.world_mm(i, j, k));
    double sum = 0, weights = 0;
    for (int c = -3; c <= 3; ++c)  // across: +-1.5 FWHM, sigma = FWHM / 2.355
      for (int b = -1; b <= 1; ++b)
        for (int a = -1; a <= 1; ++a) {
          const double t = 0.5 * c;  // slices
          const double w = std::exp(-0.5 * t * t * 2.3548 * 2.3548);
          sum += w * at(g.world_mm(i + a / 3.0, j + b / 3.0, k + t));
          weights += w;
        }
    return sum / weights;
  }

  // Tilted around the brain's centre. Noise: Rician, noise_fraction of the
  // brain's p99.
  static Crop make_crop(bool deform, double bias_amplitude, double noise_fraction, const Scanner& scanner = {}) {
    const Eigen::Matrix3d tilt =
        Eigen::AngleAxisd(10 * M_PI / 180, Eigen::Vector3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
    const Grid3 g = test::make_grid(scanner.dims, scanner.spacing_mm, tilt, centre_);
    Crop c{ImageF(g), LabelImage(g), ImageF(), VectorImage3(g)};
    const LinearSampler t1(*t1_), brain(*brain_);
    std::mt19937_64 rng(7);
    std::normal_distribution<double> normal(0, 1);
    const double sigma = noise_fraction * p99_;  // Rician, as the phantom's
    Mask inside(g, 0);
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          const Eigen::Vector3d x = g.world_mm(i, j, k);
          const Eigen::Vector3d u = deform ? true_pullback_mm(x, centre_) : Eigen::Vector3d::Zero();
          double in_brain = 0;
          const double value = voxel_value(t1, g, i, j, k, deform, scanner.partial_volume);
          brain.sample(x + u, &in_brain, nullptr);
          const double bias = std::exp(bias_amplitude * (i / (g.dims[0] - 1.0) - 0.5 + 0.5 * (k / (g.dims[2] - 1.0) - 0.5)));
          const double re = bias * value + sigma * normal(rng), im = sigma * normal(rng);
          c.intraop_t1.at(i, j, k) = static_cast<float>(sigma > 0 ? std::sqrt(re * re + im * im) : bias * value);
          c.labels.at(i, j, k) = in_brain > 0.5 ? 1 : 0;
          inside.at(i, j, k) = c.labels.at(i, j, k);
          c.truth_mm.vectors[g.index(i, j, k)] = u.cast<float>();
        }
    c.brain_sdf_mm = signed_distance_mm(fill_holes(inside));
    return c;
  }

  static IntensityRefinementReport refine(const Crop& c, VectorImage3* u) {
    const IntensityRefinementInput in{c.intraop_t1, c.labels, c.brain_sdf_mm, *t1_, {1}, 0};
    return refine_with_intensity(*u, in, IntensityRefinementParameters{});
  }

  // Mean |a - b| over brain voxels at least margin_mm inside the brain and
  // away from the crop's faces (where the image can only see one side).
  static double mean_difference_mm(const Crop& c, const VectorImage3& a, const VectorImage3& b, double margin_mm) {
    const Grid3& g = c.labels.grid;
    const Eigen::Vector3d sp = g.spacing_mm();
    double sum = 0;
    std::size_t n = 0;
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          const int idx[3] = {i, j, k};
          bool away = true;
          for (int ax = 0; ax < 3; ++ax)
            away = away && std::min(idx[ax], g.dims[ax] - 1 - idx[ax]) * sp[ax] >= margin_mm;
          const std::size_t v = g.index(i, j, k);
          if (!away || c.labels.voxels[v] == 0 || c.brain_sdf_mm.voxels[v] > -margin_mm) continue;
          sum += (a.vectors[v] - b.vectors[v]).norm();
          ++n;
        }
    EXPECT_GT(n, 20000u);
    return sum / static_cast<double>(n);
  }

  static inline ImageF* t1_ = nullptr;
  static inline ImageF* brain_ = nullptr;
  static inline Eigen::Vector3d centre_ = Eigen::Vector3d::Zero();
  static inline double p99_ = 0;     // of the T1 in the brain
  static inline double median_ = 0;  // likewise
};

TEST_F(IntensityRefinementTest, RecoversAKnownSmoothDeformationUnderBiasAndNoise) {
  const Crop c = make_crop(/*deform=*/true, /*bias_amplitude=*/0.25, /*noise_fraction=*/0.03);
  VectorImage3 u(c.labels.grid);  // 0: the model knew nothing of this motion
  const double before = mean_difference_mm(c, u, c.truth_mm, 8.0);
  const IntensityRefinementReport r = refine(c, &u);
  const double after = mean_difference_mm(c, u, c.truth_mm, 8.0);
  ASSERT_TRUE(r.applied) << r.skipped_reason;
  EXPECT_GT(before, 1.0) << "the test field must be a few mm";
  EXPECT_LT(after, before / 3) << "mean error " << before << " -> " << after << " mm";
  std::printf("mean error %.3f -> %.3f mm, max change %.2f mm, %d iterations\n", before, after, r.max_correction_mm, r.iterations);
  EXPECT_LT(r.rms_residual_after, r.rms_residual_before);
  EXPECT_GT(r.samples, 10000u);
  EXPECT_LE(r.max_correction_mm, 3.0 + 1e-6) << "|v| is bounded by max_correction_mm (u = 0: no stretch)";
}

TEST_F(IntensityRefinementTest, LeavesAnIdenticalPairAlone) {
  const Crop c = make_crop(/*deform=*/false, 0.0, 0.0);
  VectorImage3 u(c.labels.grid);
  // This "scan" samples the preop at voxel centres, with no point-spread
  // function of its own: compared with the preop as it is, the pair is
  // identical to the last bit.
  IntensityRefinementParameters p;
  p.match_point_spread = false;
  const IntensityRefinementReport r =
      refine_with_intensity(u, IntensityRefinementInput{c.intraop_t1, c.labels, c.brain_sdf_mm, *t1_, {1}, 0}, p);
  ASSERT_TRUE(r.applied) << r.skipped_reason;
  EXPECT_LT(r.max_correction_mm, 0.01);
  double largest = 0;
  for (const auto& v : u.vectors) largest = std::max(largest, static_cast<double>(v.norm()));
  EXPECT_LT(largest, 0.01) << "also outside the brain";
}

TEST_F(IntensityRefinementTest, NoiseAndBiasAloneMoveAnIdenticalPairLittle) {
  const Crop c = make_crop(/*deform=*/false, 0.25, 0.05);
  VectorImage3 u(c.labels.grid);
  const IntensityRefinementReport r = refine(c, &u);
  ASSERT_TRUE(r.applied) << r.skipped_reason;
  EXPECT_LT(mean_difference_mm(c, u, VectorImage3(c.labels.grid), 8.0), 0.15);
  EXPECT_LT(r.max_correction_mm, 0.6);
}

// A 0.15 T-like scan: 1.7 x 1.7 x 2.4 mm voxels that integrate the scene
// (partial volume), SNR 7 at the tissue's median, a +-40 % bias. The noise
// enters the data term as 1 / sigma^2; with fixed regulariser weights the
// prior then outweighs the image about tenfold against a 1.5 T scan and the
// correction stays near the FEM's answer. Relative to the data's own
// curvature (smoothing_length_mm), the image decides the same features at
// any noise level.
Scanner low_field() {
  Scanner s;
  s.dims = {56, 56, 36};
  s.spacing_mm = {1.7, 1.7, 2.4};
  s.partial_volume = true;
  return s;
}

TEST_F(IntensityRefinementTest, RecoversAKnownDeformationFromALowFieldScan) {
  const Crop c = make_crop(/*deform=*/true, /*bias_amplitude=*/std::log(1.4), median_ / 7 / p99_, low_field());
  const IntensityRefinementInput in{c.intraop_t1, c.labels, c.brain_sdf_mm, *t1_, {1}, 0};
  VectorImage3 u(c.labels.grid), fixed(c.labels.grid);  // 0: the model knew nothing of this motion
  const double before = mean_difference_mm(c, u, c.truth_mm, 8.0);
  const IntensityRefinementReport r = refine_with_intensity(u, in, IntensityRefinementParameters{});
  IntensityRefinementParameters old_weights;
  old_weights.smoothing_length_mm = 0;  // the fixed membrane and shrink weights
  old_weights.match_point_spread = false;
  const IntensityRefinementReport rf = refine_with_intensity(fixed, in, old_weights);
  IntensityRefinementParameters sharp;  // the new prior against the sharp preop
  sharp.match_point_spread = false;
  VectorImage3 unblurred(c.labels.grid);
  ASSERT_TRUE(refine_with_intensity(unblurred, in, sharp).applied);
  const double after_sharp = mean_difference_mm(c, unblurred, c.truth_mm, 8.0);
  ASSERT_TRUE(r.applied) << r.skipped_reason;
  ASSERT_TRUE(rf.applied) << rf.skipped_reason;
  const double after = mean_difference_mm(c, u, c.truth_mm, 8.0), after_fixed = mean_difference_mm(c, fixed, c.truth_mm, 8.0);
  std::printf("low field: mean error %.3f -> %.3f mm (sharp preop %.3f, fixed weights %.3f), curvature %.3f / mm^2, "
              "length %.2f mm\n", before, after, after_sharp, after_fixed, r.data_curvature_per_mm2, r.smoothing_length_mm);
  EXPECT_LE(after, after_sharp) << "the preop at the scanner's resolution must not do worse than the sharp one";
  EXPECT_LT(after, before / 2) << "mean error " << before << " -> " << after << " mm";
  EXPECT_LT(after, 0.8 * after_fixed) << "the data-relative prior must recover more than the fixed weights";
  EXPECT_GT(r.smoothing_length_mm, 0.0);
}

TEST_F(IntensityRefinementTest, LowFieldNoiseAloneMovesAnIdenticalPairLittle) {
  const Crop c = make_crop(/*deform=*/false, std::log(1.4), median_ / 7 / p99_, low_field());
  VectorImage3 u(c.labels.grid);
  const IntensityRefinementReport r = refine(c, &u);
  ASSERT_TRUE(r.applied) << r.skipped_reason;
  const double moved = mean_difference_mm(c, u, VectorImage3(c.labels.grid), 8.0);
  std::printf("low field, identical pair: mean move %.3f mm, max %.2f mm\n", moved, r.max_correction_mm);
  // Below the position uncertainty of the grid itself (1.7 mm / sqrt(12)).
  EXPECT_LT(moved, 1.7 / std::sqrt(12.0));
  // A far noisier image that is still trusted (SNR 3), and few samples: so
  // little information per mm^3 that the noise floor lengthens the smoothing
  // and holds v as still.
  const Crop faint = make_crop(/*deform=*/false, std::log(1.4), median_ / 3 / p99_, low_field());
  VectorImage3 w(faint.labels.grid);
  IntensityRefinementParameters few;
  few.max_samples = 1000;
  const IntensityRefinementReport rw = refine_with_intensity(
      w, IntensityRefinementInput{faint.intraop_t1, faint.labels, faint.brain_sdf_mm, *t1_, {1}, 0}, few);
  ASSERT_TRUE(rw.applied) << rw.skipped_reason << " (explained " << rw.explained_variance << ")";
  const double faint_moved = mean_difference_mm(faint, w, VectorImage3(faint.labels.grid), 8.0);
  std::printf("SNR 3, identical pair: mean move %.3f mm, curvature %.4f / mm^2, length %.2f mm\n", faint_moved,
              rw.data_curvature_per_mm2, rw.smoothing_length_mm);
  EXPECT_GT(rw.smoothing_length_mm, IntensityRefinementParameters{}.smoothing_length_mm) << "the noise floor binds";
  EXPECT_LT(faint_moved, 1.7 / std::sqrt(12.0));
}

TEST_F(IntensityRefinementTest, AnImageUnrelatedToThePreopIsNotTrusted) {
  Crop shuffled = make_crop(/*deform=*/true, 0.1, 0.03);
  std::vector<std::size_t> brain;
  for (std::size_t v = 0; v < shuffled.labels.voxels.size(); ++v)
    if (shuffled.labels.voxels[v]) brain.push_back(v);
  std::vector<float> values;
  for (auto v : brain) values.push_back(shuffled.intraop_t1.voxels[v]);
  std::shuffle(values.begin(), values.end(), std::mt19937_64(3));
  for (std::size_t n = 0; n < brain.size(); ++n) shuffled.intraop_t1.voxels[brain[n]] = values[n];
  VectorImage3 u(shuffled.labels.grid);
  const IntensityRefinementReport r = refine(shuffled, &u);
  EXPECT_FALSE(r.applied);
  EXPECT_FALSE(r.skipped_reason.empty());
  for (const auto& v : u.vectors) ASSERT_EQ(v, Eigen::Vector3f::Zero()) << "the field was changed";


  Crop noise = make_crop(/*deform=*/true, 0.1, 0.03);  // pure noise over the tissue's intensity range
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> uniform(0.2, 1.0);
  for (auto v : brain) noise.intraop_t1.voxels[v] = static_cast<float>(uniform(rng) * p99_);
  const IntensityRefinementReport rn = refine(noise, &u);
  EXPECT_FALSE(rn.applied);
  EXPECT_LT(rn.explained_variance, 0.1) << rn.skipped_reason;
  for (const auto& v : u.vectors) ASSERT_EQ(v, Eigen::Vector3f::Zero()) << "the field was changed";

  Crop other = make_crop(/*deform=*/true, 0.1, 0.03);  // another head: the anatomy 30 mm away
  const LinearSampler t1(*t1_);
  const Grid3& g = other.labels.grid;
  for (auto v : brain) {
    double value = 0;
    const int i = static_cast<int>(v % g.dims[0]), j = static_cast<int>(v / g.dims[0] % g.dims[1]),
              k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    t1.sample(g.world_mm(i, j, k) + Eigen::Vector3d(0, 30, 0), &value, nullptr);
    other.intraop_t1.voxels[v] = static_cast<float>(value);
  }
  const IntensityRefinementReport ro = refine(other, &u);
  EXPECT_FALSE(ro.applied) << "explained " << ro.explained_variance << " by " << ro.bias_model;
  for (const auto& v : u.vectors) ASSERT_EQ(v, Eigen::Vector3f::Zero()) << "the field was changed";
  std::printf("explained: noise %.3f, another head %.3f\n", rn.explained_variance, ro.explained_variance);
}

// A T2-like contrast (bright fluid, dark white matter): an inverting,
// non-linear map of the preop T1 no positive bias of P can explain; the
// transfer function f(P) recovers the relation and the motion.
TEST_F(IntensityRefinementTest, RecoversMotionFromAnInvertedNonLinearContrast) {
  Crop c = make_crop(/*deform=*/true, /*bias_amplitude=*/0.0, /*noise_fraction=*/0.0);
  std::mt19937_64 rng(11);
  std::normal_distribution<double> normal(0, 1);
  const Grid3& g = c.labels.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const double t = std::clamp(c.intraop_t1.at(i, j, k) / p99_, 0.0, 1.0);
        const double t2 = p99_ * (0.15 + 0.85 * std::pow(1.0 - t, 1.5));  // inverted, curved
        const double bias = std::exp(0.25 * (j / 79.0 - 0.5 - 0.5 * (k / 35.0 - 0.5)));
        const double sigma = 0.03 * p99_;
        const double re = bias * t2 + sigma * normal(rng), im = sigma * normal(rng);
        c.intraop_t1.at(i, j, k) = static_cast<float>(std::sqrt(re * re + im * im));
      }
  VectorImage3 u(g);
  const double before = mean_difference_mm(c, u, c.truth_mm, 8.0);
  const IntensityRefinementReport r = refine(c, &u);
  ASSERT_TRUE(r.applied) << r.skipped_reason;
  EXPECT_NE(r.bias_model.find("f(P)"), std::string::npos) << r.bias_model;
  EXPECT_GT(r.explained_variance, 0.5);
  const double after = mean_difference_mm(c, u, c.truth_mm, 8.0);
  std::printf("T2-like: mean error %.3f -> %.3f mm, explained %.2f, %d iterations\n", before, after,
              r.explained_variance, r.iterations);
  EXPECT_LT(after, before / 2) << "mean error " << before << " -> " << after << " mm";
  EXPECT_LT(r.rms_residual_after, r.rms_residual_before);
}

TEST_F(IntensityRefinementTest, BadInputsAreClearErrors) {
  const Crop c = make_crop(false, 0.0, 0.0);
  VectorImage3 u(c.labels.grid);
  IntensityRefinementParameters p;
  p.lattice_spacing_mm = 0.5;
  const IntensityRefinementInput in{c.intraop_t1, c.labels, c.brain_sdf_mm, *t1_, {1}, 0};
  EXPECT_THROW(refine_with_intensity(u, in, p), InputError);
  ImageF wrong = c.intraop_t1;
  wrong.grid.world_from_voxel(0, 3) += 3.0;
  const IntensityRefinementInput moved{wrong, c.labels, c.brain_sdf_mm, *t1_, {1}, 0};
  EXPECT_THROW(refine_with_intensity(u, moved, IntensityRefinementParameters{}), InputError);
}

// The pipeline keeps the blurred preop between passes and scans on grids of
// the same resolution: handed in, it gives the field blurring here gives,
// and the blur depends on the grid's spacing and axes, not on its position.
TEST_F(IntensityRefinementTest, ABlurredPreopHandedInGivesTheSameField) {
  const Crop c = make_crop(/*deform=*/true, 0.1, 0.02, low_field());
  const IntensityRefinementInput in{c.intraop_t1, c.labels, c.brain_sdf_mm, *t1_, {1}, 0};
  VectorImage3 here(c.labels.grid), handed(c.labels.grid);
  ASSERT_TRUE(refine_with_intensity(here, in, IntensityRefinementParameters{}).applied);
  Grid3 shifted = c.labels.grid;
  shifted.world_from_voxel.col(3).head<3>() += Eigen::Vector3d(13.0, -7.0, 4.5);
  EXPECT_EQ(preop_point_spread_sigma_voxels(t1_->grid, shifted), preop_point_spread_sigma_voxels(t1_->grid, c.labels.grid));
  const ImageF blurred = preop_at_intraop_resolution(*t1_, shifted);
  IntensityRefinementInput with = in;
  with.preop_t1_at_resolution = &blurred;
  ASSERT_TRUE(refine_with_intensity(handed, with, IntensityRefinementParameters{}).applied);
  for (std::size_t v = 0; v < here.vectors.size(); ++v) ASSERT_EQ(here.vectors[v], handed.vectors[v]) << v;
  // It is what the refinement compares with: the sharp preop handed in
  // instead gives another field.
  with.preop_t1_at_resolution = t1_;
  VectorImage3 sharp(c.labels.grid);
  ASSERT_TRUE(refine_with_intensity(sharp, with, IntensityRefinementParameters{}).applied);
  double largest_difference_mm = 0;
  for (std::size_t v = 0; v < here.vectors.size(); ++v)
    largest_difference_mm = std::max(largest_difference_mm, double((here.vectors[v] - sharp.vectors[v]).norm()));
  EXPECT_GT(largest_difference_mm, 1e-3);
  // A coarser grid blurs more; another preop grid is refused.
  Grid3 coarser = c.labels.grid;
  coarser.world_from_voxel.topLeftCorner<3, 3>() *= 1.5;
  EXPECT_GT(preop_point_spread_sigma_voxels(t1_->grid, coarser).sum(),
            preop_point_spread_sigma_voxels(t1_->grid, c.labels.grid).sum());
  const ImageF wrong(c.intraop_t1.grid, 1.f);
  with.preop_t1_at_resolution = &wrong;
  EXPECT_THROW(refine_with_intensity(handed, with, IntensityRefinementParameters{}), InputError);
}

TEST_F(IntensityRefinementTest, WithoutTissueLabelsNothingIsDone) {
  const Crop c = make_crop(true, 0.0, 0.0);
  VectorImage3 u(c.labels.grid);
  const IntensityRefinementInput in{c.intraop_t1, c.labels, c.brain_sdf_mm, *t1_, {7}, 0};  // no voxel has label 7
  const IntensityRefinementReport r = refine_with_intensity(u, in, IntensityRefinementParameters{});
  EXPECT_FALSE(r.applied);
  EXPECT_NE(r.skipped_reason.find("too few"), std::string::npos) << r.skipped_reason;
  for (const auto& v : u.vectors) ASSERT_EQ(v, Eigen::Vector3f::Zero());
}

}  // namespace
}  // namespace brainshift
