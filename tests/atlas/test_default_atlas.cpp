// The default atlas built from the real Colin27 templates: anatomical sanity
// checks on each label, and the cache's round trip and recovery.
#include <gtest/gtest.h>

#include <fstream>
#include <memory>
#include <unistd.h>

#include "atlas/default_atlas.h"
#include "core/errors.h"
#include "core/label_colour.h"
#include "core/timer.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "temp_dir.h"  // tests/support

namespace brainshift {
namespace {

const std::filesystem::path kTemplates = "/usr/share/mricron/templates";

class DefaultAtlasTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!std::filesystem::exists(kTemplates / "ch2.nii.gz")) return;
    cache_tmp_ = std::make_unique<test::TempDir>("atlas");
    cache_dir_ = cache_tmp_->path();
    Stopwatch sw;
    atlas_ = std::make_unique<DefaultAtlas>(load_or_build_default_atlas(cache_dir_));
    build_seconds_ = sw.seconds();
    std::printf("atlas build: %.2f s\n", build_seconds_);
  }
  static void TearDownTestSuite() {
    cache_tmp_.reset();
    atlas_.reset();
  }
  void SetUp() override {
    if (!atlas_) GTEST_SKIP() << "mricron templates not installed";
  }
  static const DefaultAtlas& atlas() { return *atlas_; }
  static Mask label(std::uint16_t l) { return mask_of_labels(atlas_->labels, {l}); }

  // Volume (ml) of the mask's voxels with world x below / above the midline.
  static std::pair<double, double> left_right_ml(const Mask& m) {
    Mask left(m.grid, 0), right(m.grid, 0);
    const Grid3& g = m.grid;
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          if (!m.at(i, j, k)) continue;
          const double x = g.world_mm(i, j, k).x();
          if (x < -1.0) left.at(i, j, k) = 1;
          if (x > 1.0) right.at(i, j, k) = 1;
        }
    return {volume_ml(left), volume_ml(right)};
  }

  static inline std::unique_ptr<test::TempDir> cache_tmp_;
  static inline std::filesystem::path cache_dir_;
  static inline std::unique_ptr<DefaultAtlas> atlas_;
  static inline double build_seconds_ = 0;
};

TEST_F(DefaultAtlasTest, OnColin27GridWithKnownLabelsOnly) {
  EXPECT_EQ(atlas().t1.grid.dims, (std::array<int, 3>{181, 217, 181}));
  EXPECT_TRUE(atlas().labels.grid.same_geometry(atlas().t1.grid));
  for (std::uint16_t v : atlas().labels.voxels) ASSERT_LE(v, atlas_labels::corticospinal_tract);
}

TEST_F(DefaultAtlasTest, BrainVolumeIsAdult) {
  Mask brain = label(atlas_labels::brain);
  for (std::size_t i = 0; i < brain.voxels.size(); ++i) brain.voxels[i] = atlas().labels.voxels[i] != 0;
  const double ml = volume_ml(brain);
  EXPECT_GT(ml, 1300.0);
  EXPECT_LT(ml, 1900.0);
  int n = 0;
  connected_components(brain, 6, &n);
  EXPECT_EQ(n, 1);
}

TEST_F(DefaultAtlasTest, LateralVentriclesPlausible) {
  const Mask v = label(atlas_labels::ventricles);
  const double ml = volume_ml(v);
  EXPECT_GT(ml, 8.0);
  EXPECT_LT(ml, 60.0);
  const auto [left, right] = left_right_ml(v);
  EXPECT_GT(left, 2.0);
  EXPECT_GT(right, 2.0);
  EXPECT_LT(std::max(left, right) / std::min(left, right), 2.0);  // roughly symmetric
  const Eigen::Vector3d c = centroid_mm(v);
  EXPECT_LT(std::abs(c.x()), 6.0);
  EXPECT_GT(c.z(), -5.0);  // above the anterior commissure level
  // Enclosed by tissue: no ventricle voxel touches the background label.
  const LabelImage& lab = atlas().labels;
  const Grid3& g = lab.grid;
  std::size_t touching = 0;
  for (int k = 1; k + 1 < g.dims[2]; ++k)
    for (int j = 1; j + 1 < g.dims[1]; ++j)
      for (int i = 1; i + 1 < g.dims[0]; ++i) {
        if (lab.at(i, j, k) != atlas_labels::ventricles) continue;
        touching += lab.at(i - 1, j, k) == 0 || lab.at(i + 1, j, k) == 0 || lab.at(i, j - 1, k) == 0 ||
                    lab.at(i, j + 1, k) == 0 || lab.at(i, j, k - 1) == 0 || lab.at(i, j, k + 1) == 0;
      }
  EXPECT_EQ(touching, 0u);
  // The 3rd ventricle (midline, between the thalami, below the lateral
  // ventricles' bodies) is not labelled as lateral ventricle.
  std::size_t third = 0;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        if (lab.at(i, j, k) != atlas_labels::ventricles) continue;
        const Eigen::Vector3d w = g.world_mm(i, j, k);
        third += std::abs(w.x()) < 2.5 && w.y() > -30 && w.y() < 0 && w.z() < 8;
      }
  EXPECT_LT(third, 50u);
}

TEST_F(DefaultAtlasTest, CorticospinalTractBilateralFromBrainstemToCoronaRadiata) {
  const Mask cst = label(atlas_labels::corticospinal_tract);
  const auto [left, right] = left_right_ml(cst);
  EXPECT_GT(left, 3.0);
  EXPECT_GT(right, 3.0);
  const VoxelBox box = bounding_box_voxels(cst);
  ASSERT_FALSE(box.empty);
  const double z_lo = atlas().t1.grid.world_mm(0, 0, box.lo[2]).z();
  const double z_hi = atlas().t1.grid.world_mm(0, 0, box.hi[2]).z();
  EXPECT_GT(z_hi - z_lo, 60.0);
  EXPECT_LT(z_lo, -30.0);  // reaches the brainstem
  EXPECT_GT(z_hi, 20.0);   // and the corona radiata
}

TEST_F(DefaultAtlasTest, CacheReloadsIdenticalImages) {
  Stopwatch sw;
  const DefaultAtlas again = load_or_build_default_atlas(cache_dir_);
  std::printf("atlas reload from cache: %.2f s (build was %.2f s)\n", sw.seconds(), build_seconds_);
  EXPECT_EQ(again.t1.grid.dims, atlas().t1.grid.dims);
  EXPECT_LT((again.t1.grid.world_from_voxel - atlas().t1.grid.world_from_voxel).cwiseAbs().maxCoeff(), 1e-5);
  EXPECT_EQ(again.t1.voxels, atlas().t1.voxels);
  EXPECT_EQ(again.labels.voxels, atlas().labels.voxels);
  EXPECT_TRUE(std::filesystem::exists(cache_dir_ / "provenance.json"));
}

TEST_F(DefaultAtlasTest, CorruptCacheIsRebuilt) {
  const auto labels_path = cache_dir_ / "labels.nii.gz";
  const auto size = std::filesystem::file_size(labels_path);
  std::filesystem::resize_file(labels_path, size / 2);
  const DefaultAtlas rebuilt = load_or_build_default_atlas(cache_dir_);
  EXPECT_EQ(rebuilt.labels.voxels, atlas().labels.voxels);
  EXPECT_EQ(std::filesystem::file_size(labels_path), size);
}

TEST(DefaultAtlasErrors, MissingTemplatesNameTheFile) {
  const test::TempDir empty("no_templates");
  try {
    build_default_atlas(empty.path());
    ADD_FAILURE() << "expected InputError";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find("ch2.nii.gz"), std::string::npos) << e.what();
  }
}

// A site's table with other values and no tract: the atlas arrives in its
// values, by name, the tract as tissue.
TEST(AtlasLabelsFor, MapsByNameAndUntrackedStructuresBecomeTissue) {
  LabelImage atlas(Grid3{}, 0);
  atlas.grid.dims = {4, 1, 1};
  atlas.voxels = {atlas_labels::background, atlas_labels::brain, atlas_labels::ventricles,
                  atlas_labels::corticospinal_tract};
  LabelTable site;
  site.entries = {{10, "parenchyma_of_site", "", LabelRole::parenchyma}, {20, "ventricles", "", LabelRole::cavity}};
  EXPECT_EQ(atlas_labels_for(atlas, site).voxels, (std::vector<std::uint16_t>{0, 10, 20, 10}));
  site.entries.push_back({30, "corticospinal_tract", "cst"});
  EXPECT_EQ(atlas_labels_for(atlas, site).voxels, (std::vector<std::uint16_t>{0, 10, 20, 30}));
  EXPECT_THROW(atlas_labels_for(atlas, LabelTable{}), InputError);
}

}  // namespace
}  // namespace brainshift
