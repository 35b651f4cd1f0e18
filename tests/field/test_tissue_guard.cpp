// The field beyond the brain must not pull preop tissue out of it
// (field/tissue_guard.h): a brain sunk by 20 mm leaves a gap where the preop
// brain was; the fade beyond the mesh pulled that gap back into the preop
// brain, the guard keeps it out, without touching the mesh's own field and
// without seams.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>

#include "box_mesh.h"
#include "core/errors.h"
#include "field/displacement_field.h"
#include "field/tissue_guard.h"
#include "field/warp.h"

namespace brainshift {
namespace {

using test::kuhn_box;
using test::oblique_grid;

// The preop brain: the box [-20, 20] x [-18, 22] x [-16, 24] mm, label 1 on a
// 1 mm preop grid; sunk 20 mm down (z) it fills z in [-36, 4] and leaves the
// gap z in (4, 24].
struct SunkBox {
  TetMesh mesh = kuhn_box(Eigen::Vector3d(-20, -18, -16), {8, 8, 8}, 5.0);
  Grid3 grid = oblique_grid({70, 64, 40}, Eigen::Vector3d(1.1, 1.2, 2.4), Eigen::Vector3d(-35, -45, -48), 0.3);
  Eigen::Vector3d lo{-20, -18, -16}, hi{20, 22, 24};
  double sink_mm = 20.0;
  LabelImage preop_labels;
  Mask outline;
  MeshDeformation deformation;

  SunkBox() {
    Grid3 preop;
    preop.dims = {60, 60, 60};
    preop.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-30, -30, -30);
    preop_labels = LabelImage(preop, 0);
    for (int k = 0; k < 60; ++k)
      for (int j = 0; j < 60; ++j)
        for (int i = 0; i < 60; ++i)
          preop_labels.at(i, j, k) = inside_preop(preop.world_mm(i, j, k), 0.0) ? 1 : 0;
    outline = Mask(grid, 0);
    for (int k = 0; k < grid.dims[2]; ++k)
      for (int j = 0; j < grid.dims[1]; ++j)
        for (int i = 0; i < grid.dims[0]; ++i)
          outline.at(i, j, k) = inside_preop(grid.world_mm(i, j, k) + Eigen::Vector3d(0, 0, sink_mm), 0.0);
    deformation.nonrigid_mm.assign(mesh.node_count(), Eigen::Vector3d(0, 0, -sink_mm));
  }
  // Inside the preop box by more than margin_mm.
  bool inside_preop(const Eigen::Vector3d& p, double margin_mm) const {
    return (p - lo).minCoeff() > margin_mm && (hi - p).minCoeff() > margin_mm;
  }
};

struct Outside {
  std::size_t in_preop_tissue = 0;  // voxels beyond the mesh and the outline pulled back into the preop box
  double max_step_jump_mm = 0;      // the largest change of u between z-neighbours beyond the mesh
};

Outside beyond_the_brain(const SunkBox& s, const VectorImage3& u, const Mask& mesh_region) {
  Outside o;
  const Grid3& g = s.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        if (mesh_region.voxels[v] || s.outline.voxels[v]) continue;
        // 1 mm inside: the guard decides by the nearest preop voxel.
        if (s.inside_preop(g.world_mm(i, j, k) + u.vectors[v].cast<double>(), 1.0)) ++o.in_preop_tissue;
        if (k + 1 < g.dims[2] && !mesh_region.voxels[g.index(i, j, k + 1)])
          o.max_step_jump_mm = std::max(o.max_step_jump_mm, static_cast<double>((u.vectors[g.index(i, j, k + 1)] - u.vectors[v]).norm()));
      }
  return o;
}

TEST(TissueGuard, TheGapASinkingLeftNoLongerPullsBackIntoThePreopBrain) {
  SunkBox s;
  FieldStats plain_stats, guarded_stats;
  Mask plain_region, guarded_region;
  const VectorImage3 plain = pullback_field(s.mesh, s.deformation, s.grid, FieldParameters{}, &plain_stats, &plain_region);
  const TissueGuard guard{&s.preop_labels, tissue_voxel_box(s.preop_labels), &s.outline};
  const VectorImage3 guarded =
      pullback_field(s.mesh, s.deformation, s.grid, FieldParameters{}, &guarded_stats, &guarded_region, &guard);
  const Outside before = beyond_the_brain(s, plain, plain_region), after = beyond_the_brain(s, guarded, guarded_region);
  std::printf("voxels beyond the brain pulled into preop tissue: %zu -> %zu; landing %zu, raised %zu, unresolved %zu; "
              "largest z-step jump %.2f -> %.2f mm\n",
              before.in_preop_tissue, after.in_preop_tissue, guarded_stats.guard_landing_voxels,
              guarded_stats.guard_raised_voxels, guarded_stats.guard_unresolved_voxels, before.max_step_jump_mm,
              after.max_step_jump_mm);
  // The fade pulls the gap (20 mm deep, 40 x 40 mm) back into the brain ...
  EXPECT_GT(before.in_preop_tissue, 2000u);
  // ... the guard holds all of it out, each landing resolved.
  EXPECT_EQ(after.in_preop_tissue, 0u);
  EXPECT_GT(guarded_stats.guard_landing_voxels, 2000u);
  EXPECT_EQ(guarded_stats.guard_unresolved_voxels, 0u);
  // The mesh's own field is untouched, and the guard's spread makes no seam
  // steeper than the fade's own.
  ASSERT_EQ(plain_region.voxels, guarded_region.voxels);
  double inside_change = 0;
  for (std::size_t v = 0; v < plain.vectors.size(); ++v)
    if (plain_region.voxels[v]) inside_change = std::max(inside_change, static_cast<double>((plain.vectors[v] - guarded.vectors[v]).norm()));
  EXPECT_LT(inside_change, 1e-5);
  EXPECT_LE(after.max_step_jump_mm, before.max_step_jump_mm + 0.5);
  // What a viewer draws: the preop labels warped through the field hold no
  // tissue in the gap.
  std::size_t plain_gap = 0, guarded_gap = 0;
  const LabelImage plain_warped = warp_labels_nearest(s.preop_labels, plain);
  const LabelImage guarded_warped = warp_labels_nearest(s.preop_labels, guarded);
  for (std::size_t v = 0; v < plain.vectors.size(); ++v) {
    if (plain_region.voxels[v] || s.outline.voxels[v]) continue;
    const Eigen::Vector3d x = s.grid.world_mm(v % s.grid.dims[0], (v / s.grid.dims[0]) % s.grid.dims[1],
                                              v / (static_cast<std::size_t>(s.grid.dims[0]) * s.grid.dims[1]));
    if (!s.inside_preop(x, 1.0)) continue;  // the gap: where the preop brain was
    plain_gap += plain_warped.voxels[v] != 0;
    guarded_gap += guarded_warped.voxels[v] != 0;
  }
  std::printf("gap voxels drawn as tissue: %zu -> %zu\n", plain_gap, guarded_gap);
  EXPECT_GT(plain_gap, 1000u);
  EXPECT_EQ(guarded_gap, 0u);
}

TEST(TissueGuard, AFieldThatPullsNothingIntoTissueIsLeftAsItWas) {
  SunkBox s;
  s.deformation.nonrigid_mm.assign(s.mesh.node_count(), Eigen::Vector3d(0, 0, 3.0));  // a 3 mm rise: no gap
  for (auto& m : s.outline.voxels) m = 0;
  for (int k = 0; k < s.grid.dims[2]; ++k)
    for (int j = 0; j < s.grid.dims[1]; ++j)
      for (int i = 0; i < s.grid.dims[0]; ++i)
        s.outline.at(i, j, k) = s.inside_preop(s.grid.world_mm(i, j, k) - Eigen::Vector3d(0, 0, 3.0), 0.0);
  FieldStats stats;
  const VectorImage3 plain = pullback_field(s.mesh, s.deformation, s.grid, FieldParameters{});
  const TissueGuard guard{&s.preop_labels, tissue_voxel_box(s.preop_labels), &s.outline};
  const VectorImage3 guarded = pullback_field(s.mesh, s.deformation, s.grid, FieldParameters{}, &stats, nullptr, &guard);
  EXPECT_EQ(stats.guard_raised_voxels, 0u);
  double change = 0;
  for (std::size_t v = 0; v < plain.vectors.size(); ++v)
    change = std::max(change, static_cast<double>((plain.vectors[v] - guarded.vectors[v]).norm()));
  EXPECT_LT(change, 1e-4);
}

// A segmentation's outline is uncertain by a voxel or so: the preop tissue
// here reaches 2 mm beyond the mesh (a rim the mesh and the outline leave
// out), and the brain moved 3 mm sideways. The rim beyond the moved mesh
// rightly pulls back into that tissue; within the outline's tolerance it is
// not judged, beyond it every landing is (the tissue's 2 mm plus its
// voxel's rounding: a few corner voxels just beyond 3 mm).
TEST(TissueGuard, AVoxelWithinTheOutlinesToleranceIsNotJudged) {
  SunkBox s;
  s.lo -= Eigen::Vector3d::Constant(2.0), s.hi += Eigen::Vector3d::Constant(2.0);
  SunkBox grown;  // preop tissue of the larger box, outline of the mesh moved 3 mm along x
  for (int k = 0; k < 60; ++k)
    for (int j = 0; j < 60; ++j)
      for (int i = 0; i < 60; ++i)
        grown.preop_labels.at(i, j, k) = s.inside_preop(grown.preop_labels.grid.world_mm(i, j, k), 0.0) ? 1 : 0;
  const Eigen::Vector3d shift(3.0, 0, 0);
  grown.deformation.nonrigid_mm.assign(grown.mesh.node_count(), shift);
  for (int k = 0; k < grown.grid.dims[2]; ++k)
    for (int j = 0; j < grown.grid.dims[1]; ++j)
      for (int i = 0; i < grown.grid.dims[0]; ++i)
        grown.outline.at(i, j, k) = grown.inside_preop(grown.grid.world_mm(i, j, k) - shift, 0.0);
  FieldStats strict, tolerant;
  const TissueGuard judged{&grown.preop_labels, tissue_voxel_box(grown.preop_labels), &grown.outline, 0.0};
  const TissueGuard within{&grown.preop_labels, tissue_voxel_box(grown.preop_labels), &grown.outline, 3.0};
  pullback_field(grown.mesh, grown.deformation, grown.grid, FieldParameters{}, &strict, nullptr, &judged);
  pullback_field(grown.mesh, grown.deformation, grown.grid, FieldParameters{}, &tolerant, nullptr, &within);
  std::printf("rim voxels landing in tissue: judged %zu (unresolved %zu), within a 3 mm tolerance %zu\n",
              strict.guard_landing_voxels, strict.guard_unresolved_voxels, tolerant.guard_landing_voxels);
  EXPECT_GT(strict.guard_unresolved_voxels, 1000u);
  // Left: the box's corners just beyond the tolerance (the 2.4 mm slices).
  EXPECT_LT(tolerant.guard_landing_voxels * 20, strict.guard_landing_voxels);
}

TEST(TissueGuard, AGuardWithoutItsOutlineIsRefused) {
  SunkBox s;
  const TissueGuard no_outline{&s.preop_labels, tissue_voxel_box(s.preop_labels), nullptr};
  EXPECT_THROW(pullback_field(s.mesh, s.deformation, s.grid, FieldParameters{}, nullptr, nullptr, &no_outline),
               InputError);
  const Mask other(oblique_grid({10, 10, 10}, Eigen::Vector3d(1, 1, 1), Eigen::Vector3d::Zero(), 0.0), 0);
  const TissueGuard wrong_grid{&s.preop_labels, tissue_voxel_box(s.preop_labels), &other};
  EXPECT_THROW(pullback_field(s.mesh, s.deformation, s.grid, FieldParameters{}, nullptr, nullptr, &wrong_grid),
               InputError);
}

}  // namespace
}  // namespace brainshift
