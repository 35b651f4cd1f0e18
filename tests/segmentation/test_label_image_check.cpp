// The labels-vs-image check on its own coarse grid (label_image_check.h):
// the small synthetic head with scanner-like noise, its own labels pass; the
// labels grown by 6 mm into what the image shows as outside fail with the
// leak's volume and depth; labels on another grid are an input error.
#include <gtest/gtest.h>

#include <random>

#include "core/errors.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "segmentation/label_image_check.h"
#include "synthetic_head.h"

using namespace brainshift;
using namespace brainshift::segmentation;

namespace {

struct Case {
  ImageF image;
  LabelImage labels;
};

Case noisy_head() {
  test::SyntheticHead h = test::synthetic_head();
  std::mt19937 rng(3);
  std::normal_distribution<float> noise(0.f, 4.f);
  for (auto& v : h.t1.voxels) v = std::max(0.f, v + noise(rng));
  return {std::move(h.t1), std::move(h.labels)};
}

LabelImageCheck check(const ImageF& image, const LabelImage& labels) {
  return check_labels_against_image(image, labels, 1, {2}, LabelImageCheckParameters{});
}

}  // namespace

TEST(LabelImageCheck, TheImagesOwnLabelsPassOnTheCoarseGrid) {
  const Case c = noisy_head();
  const LabelImageCheck r = check(c.image, c.labels);
  EXPECT_TRUE(r.failure.empty()) << r.failure;
  EXPECT_EQ(r.metrics.value("checked", false), true) << r.metrics.dump();
  // Classified on about 2 mm (whole voxels over the image's extent), not
  // the image's 1.5 mm.
  EXPECT_NEAR(r.metrics["grid_spacing_mm"][0].get<double>(), 2.0, 0.05) << r.metrics.dump();
  EXPECT_LT(r.labels_not_image.volume_ml, 0.2 * r.metrics["limit_ml"].get<double>()) << r.metrics.dump();
  EXPECT_LT(r.image_not_labels.volume_ml, 0.2 * r.metrics["limit_ml"].get<double>()) << r.metrics.dump();
}

TEST(LabelImageCheck, LabelsLeakingSixMillimetresAreAGrossDisagreement) {
  const Case c = noisy_head();
  LabelImage leak = c.labels;
  const Mask grown = dilate(mask_of_labels(c.labels, {1, 2, 4}), 6.0);
  for (std::size_t v = 0; v < grown.voxels.size(); ++v)
    if (grown.voxels[v] && leak.voxels[v] == 0) leak.voxels[v] = 1;
  const LabelImageCheck r = check(c.image, leak);
  EXPECT_FALSE(r.failure.empty()) << r.metrics.dump();
  EXPECT_GT(r.labels_not_image.volume_ml, r.metrics["limit_ml"].get<double>()) << r.metrics.dump();
  EXPECT_GT(r.labels_not_image.max_depth_mm, 4.0) << r.metrics.dump();
}

TEST(LabelImageCheck, LabelsOnAnotherGridAreAnInputError) {
  const Case c = noisy_head();
  LabelImage shifted = c.labels;
  shifted.grid.world_from_voxel(0, 3) += 3.0;
  EXPECT_THROW(check(c.image, shifted), InputError);
}
