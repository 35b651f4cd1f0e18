// Given labels that leave out fluid spaces the preop counts as brain
// (segmentation/preop_fluid_spaces.h): a synthetic head on a 1 mm grid whose
// preop brain holds a cistern of fluid open to its base; the given intraop
// labels leave out the cistern, a sinking's gap under the vertex (tissue in
// the preop) and a thin shell around the brain (a threshold's erosion).
#include <gtest/gtest.h>

#include <cmath>

#include "core/errors.h"
#include "image/morphology.h"
#include "segmentation/preop_fluid_spaces.h"

using namespace brainshift;
using namespace brainshift::segmentation;

namespace {

constexpr float kTissue = 90, kFluid = 30;
constexpr std::uint16_t kBrain = 1, kVentricle = 2;

Grid3 grid() {
  Grid3 g;
  g.dims = {80, 80, 80};
  g.world_from_voxel.block<3, 1>(0, 3) = Eigen::Vector3d(-40, -40, -40);
  return g;
}

bool in_brain(const Eigen::Vector3d& p) { return p.norm() < 32; }
bool in_ventricle(const Eigen::Vector3d& p) { return (p - Eigen::Vector3d(0, 0, 6)).norm() < 6; }
// A cistern: a vertical cylinder 10 mm wide from the base up to 12 mm deep.
bool in_cistern(const Eigen::Vector3d& p) { return std::hypot(p.x(), p.y() - 4) < 5 && p.z() < -22; }
// A gap a sinking opened: the top 12 mm of the brain under the vertex.
bool in_gap(const Eigen::Vector3d& p) { return p.z() > 20 && std::hypot(p.x(), p.y()) < 16; }

struct Scene {
  LabelImage preop_labels{grid(), 0};
  ImageF preop_t1{grid(), 0.f};
  LabelImage given{grid(), 0};
  ImageF intraop{grid(), 0.f};
};

// preop: brain with the cistern inside its label (fluid in the T1) and the
// ventricle; given: the brain without the cistern, the gap and a 1 mm shell.
Scene scene(bool cistern_fluid_in_image = true) {
  Scene s;
  const Grid3 g = grid();
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d p = g.world_mm(i, j, k);
        const std::size_t v = g.index(i, j, k);
        if (!in_brain(p)) continue;
        s.preop_labels.voxels[v] = in_ventricle(p) ? kVentricle : kBrain;
        s.preop_t1.voxels[v] = in_ventricle(p) || in_cistern(p) ? kFluid : kTissue;
        const bool left_out = in_cistern(p) || in_gap(p) || p.norm() > 31;
        s.given.voxels[v] = in_ventricle(p) ? kVentricle : left_out ? 0 : kBrain;
        const bool fluid = in_ventricle(p) || in_gap(p) || (in_cistern(p) && cistern_fluid_in_image);
        s.intraop.voxels[v] = fluid ? kFluid : kTissue;
      }
  return s;
}

PreopFluidSpaces adopt(const Scene& s, bool with_image) {
  const PreopFluidSpacesInput in{s.given,       with_image ? &s.intraop : nullptr, s.preop_labels, s.preop_t1,
                                 Eigen::Matrix4d::Identity(), kBrain, kVentricle, kFluid, kTissue};
  return adopt_preop_fluid_spaces(in, {});
}

std::size_t count_where(const LabelImage& labels, std::uint16_t value, bool (*where)(const Eigen::Vector3d&)) {
  std::size_t n = 0;
  for (int k = 0; k < labels.grid.dims[2]; ++k)
    for (int j = 0; j < labels.grid.dims[1]; ++j)
      for (int i = 0; i < labels.grid.dims[0]; ++i)
        n += labels.at(i, j, k) == value && where(labels.grid.world_mm(i, j, k)) && in_brain(labels.grid.world_mm(i, j, k));
  return n;
}

}  // namespace

TEST(PreopFluidSpaces, TheCisternIsGivenBackTheGapAndTheShellAreNot) {
  const Scene s = scene();
  for (bool with_image : {true, false}) {
    const PreopFluidSpaces r = adopt(s, with_image);
    const std::size_t cistern = count_where(s.given, 0, in_cistern);
    ASSERT_GT(cistern, 500u);
    // Nearly all of the cistern is brain again (the opening rounds its edges).
    EXPECT_GT(count_where(r.labels, kBrain, in_cistern), 0.8 * cistern) << "with image " << with_image;
    // The gap was tissue in the preop: it stays outside, every voxel of it.
    EXPECT_EQ(count_where(r.labels, kBrain, in_gap), 0u) << "with image " << with_image;
    // The 1 mm shell is narrower than a space: left as given.
    const auto shell = [](const Eigen::Vector3d& p) { return p.norm() > 31.2 && !in_cistern(p) && !in_gap(p); };
    EXPECT_EQ(count_where(r.labels, kBrain, shell), 0u);
    // Nothing else changed, and the report adds up.
    for (std::size_t v = 0; v < r.labels.voxels.size(); ++v)
      if (r.labels.voxels[v] != s.given.voxels[v]) {
        ASSERT_EQ(s.given.voxels[v], 0);
        ASSERT_EQ(r.labels.voxels[v], kBrain);
      }
    std::size_t added = 0;
    for (std::size_t v = 0; v < r.labels.voxels.size(); ++v) added += r.labels.voxels[v] != s.given.voxels[v];
    EXPECT_NEAR(r.added_ml, added / 1000.0, 1e-9);
    EXPECT_EQ(r.report["intraop_image_test"].get<bool>(), with_image);
  }
}

TEST(PreopFluidSpaces, ASpaceTheImageShowsAsTissueStaysOut) {
  // The preop's cistern holds tissue in the intraop image (say, a
  // segmenter that left out tissue for another reason): not a fluid space.
  const Scene s = scene(false);
  const PreopFluidSpaces r = adopt(s, true);
  EXPECT_EQ(count_where(r.labels, kBrain, in_cistern), 0u);
  EXPECT_EQ(r.added_ml, 0.0);
}

TEST(PreopFluidSpaces, APreopWithoutFluidContrastChangesNothing) {
  const Scene s = scene();
  const PreopFluidSpacesInput in{s.given, &s.intraop, s.preop_labels, s.preop_t1, Eigen::Matrix4d::Identity(),
                                 kBrain, kVentricle, kTissue, kTissue};
  const PreopFluidSpaces r = adopt_preop_fluid_spaces(in, {});
  EXPECT_FALSE(r.report["applied"].get<bool>());
  EXPECT_EQ(r.labels.voxels, s.given.voxels);
}

TEST(PreopFluidSpaces, AnImageOnAnotherGridIsRefused) {
  const Scene s = scene();
  ImageF other(grid(), 0.f);
  other.grid.dims = {40, 40, 40};
  other.voxels.resize(other.grid.voxel_count());
  const PreopFluidSpacesInput in{s.given, &other, s.preop_labels, s.preop_t1, Eigen::Matrix4d::Identity(),
                                 kBrain, kVentricle, kFluid, kTissue};
  EXPECT_THROW(adopt_preop_fluid_spaces(in, {}), InputError);
}
