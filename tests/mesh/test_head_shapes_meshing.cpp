// Meshing label maps of heads other than the atlas: enlarged and
// compressed ventricles, other proportions, a tumour at the ventricle wall or
// the brain surface, specks. Meshing must finish within its budgets, be
// bitwise reproducible, keep every surface and make only positive tets.
// Coarse sizes: none of these properties depends on the mesh size, and each
// case must stay at a few seconds of CPU.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <map>

#include "atlas/default_atlas.h"
#include "label_table_file.h"
#include "core/errors.h"
#include "head_shapes.h"
#include "image/morphology.h"
#include "mesh/label_mesher.h"
#include "mesh/mesh_quality.h"
#include "mesh/surface_extraction.h"
#include "phantoms.h"

namespace brainshift {
namespace {

using test::HeadLabels;

std::filesystem::path atlas_cache() {
  const char* dir = std::getenv("BRAINSHIFT_ATLAS_CACHE");
  return dir ? dir : "brainshift-atlas";
}

MeshingParameters coarse(const LabelTable& table, const LabelImage& labels) {
  MeshingParameters p;  // engine/mesh/README.md's coarse set
  p.cell_size_mm = 6.5;
  p.facet_size_mm = 3.6;
  p.facet_distance_mm = 2.0;
  p.cavity_labels = table.cavity_labels();
  p.default_tissue_label = table.brain_label();
  for (const auto l : table.resectable_labels())
    if (test::count_voxels(labels, l) > 0) p.interface_labels.push_back(l);
  return p;
}

class HeadShapes : public ::testing::TestWithParam<std::string> {
 protected:
  static void SetUpTestSuite() {
    table_ = &config::default_label_table();
    atlas_ = new LabelImage(atlas_labels_for(load_or_build_default_atlas(atlas_cache()).labels, *table_));
  }
  static void TearDownTestSuite() { delete atlas_; }
  static inline const LabelTable* table_ = nullptr;
  static inline LabelImage* atlas_ = nullptr;
};

double voxel_volume_ml(const LabelImage& labels, std::uint16_t label) {
  return static_cast<double>(test::count_voxels(labels, label)) *
         std::abs(labels.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
}

TEST_P(HeadShapes, MeshFinishesWithinBudgetReproduciblyWithEverySurface) {
  const HeadLabels l = test::head_labels_of(*table_);
  const test::HeadCase head = test::make_head_case(GetParam(), *atlas_, l);
  const MeshingParameters p = coarse(*table_, head.labels);
  MeshingStats stats;
  const TetMesh mesh = mesh_label_image(head.labels, p, &stats);

  // Budgets accounted: the refinement stayed under its cap, exudation within
  // its budget of one step per vertex.
  EXPECT_LT(stats.refined_vertices, stats.vertex_cap);
  EXPECT_EQ(stats.exude_budget, stats.refined_vertices);
  EXPECT_LE(stats.exude_steps, stats.exude_budget);
  EXPECT_EQ(stats.exude_budget_hit, stats.exude_steps == stats.exude_budget && stats.slivers_after > 0);
  EXPECT_GE(stats.min_dihedral_after_deg, stats.min_dihedral_before_deg);
  std::printf("%-26s nodes %6zu tets %7zu | refine %zu / cap %zu | exude %zu / %zu%s, slivers %zu -> %zu, "
              "min dihedral %.2f -> %.2f deg | %.2f + %.2f s\n",
              head.name.c_str(), mesh.node_count(), mesh.tet_count(), stats.refined_vertices, stats.vertex_cap,
              stats.exude_steps, stats.exude_budget, stats.exude_budget_hit ? " (budget hit)" : "",
              stats.slivers_before, stats.slivers_after, stats.min_dihedral_before_deg,
              stats.min_dihedral_after_deg, stats.seconds_refine, stats.seconds_optimise);

  // Every tet positive.
  const MeshQuality q = measure_quality(mesh);
  EXPECT_EQ(q.inverted_tets, 0u);
  EXPECT_EQ(q.degenerate_tets, 0u);
  EXPECT_GT(q.min_volume_mm3, 0.0);

  // One closed outer surface (islands are dropped), enclosing the tissue.
  const TriSurface outer = extract_boundary_surface(mesh, 0);
  EXPECT_EQ(count_connected_components(outer), 1u);
  EXPECT_NEAR(enclosed_volume_mm3(outer) / 1000.0, q.total_volume_mm3 / 1000.0 + voxel_volume_ml(head.labels, l.ventricles),
              0.05 * q.total_volume_mm3 / 1000.0);
  // The ventricles' wall: at least one closed component; what it encloses is
  // the ventricles' volume (specks of ventricle label add a few ml at most).
  const TriSurface wall = extract_boundary_surface(mesh, l.ventricles);
  EXPECT_GE(count_connected_components(wall), 1u);
  const double ventricles_ml = voxel_volume_ml(head.labels, l.ventricles);
  EXPECT_NEAR(-enclosed_volume_mm3(wall) / 1000.0, ventricles_ml, 0.2 * ventricles_ml + 1.0);
  // A tumour: its tets carry its label, their volume is its volume, and its
  // wall against the brain is made of mesh faces.
  const double tumour_ml = voxel_volume_ml(head.labels, l.tumour);
  if (tumour_ml > 1.0) {
    double meshed_ml = 0;
    for (std::size_t t = 0; t < mesh.tet_count(); ++t)
      if (mesh.tet_labels[t] == l.tumour) meshed_ml += tet_volume_mm3(mesh, t) / 1000.0;
    EXPECT_NEAR(meshed_ml, tumour_ml, 0.15 * tumour_ml + 0.5);
    EXPECT_FALSE(extract_interface_surface(mesh, l.tumour).triangles.empty());
  }

  // Bitwise reproducible.
  const TetMesh again = mesh_label_image(head.labels, p);
  ASSERT_EQ(again.node_count(), mesh.node_count());
  for (std::size_t n = 0; n < mesh.node_count(); ++n) ASSERT_EQ(again.nodes_mm[n], mesh.nodes_mm[n]) << n;
  EXPECT_EQ(again.tets, mesh.tets);
  EXPECT_EQ(again.tet_labels, mesh.tet_labels);
}

INSTANTIATE_TEST_SUITE_P(OtherHeads, HeadShapes, ::testing::ValuesIn(test::head_case_names()),
                         [](const auto& info) {
                           std::string name = info.param;
                           for (auto& c : name)
                             if (!std::isalnum(static_cast<unsigned char>(c))) c = '_';
                           return name;
                         });

// The shapes are what their names say.
TEST_F(HeadShapes, ShapesChangeTheAnatomyAsNamed) {
  const HeadLabels l = test::head_labels_of(*table_);
  const double v0 = voxel_volume_ml(*atlas_, l.ventricles);
  for (const double factor : {1.8, 2.4}) {
    const LabelImage big = test::enlarge_ventricles(*atlas_, l, factor);
    EXPECT_NEAR(voxel_volume_ml(big, l.ventricles) / v0, factor, 0.001);
  }
  const LabelImage squeezed = test::make_head_case("compressed_ventricles", *atlas_, l).labels;
  EXPECT_LT(voxel_volume_ml(squeezed, l.ventricles), 0.7 * v0);
  EXPECT_NEAR(voxel_volume_ml(squeezed, l.tumour), 4.0 / 3.0 * M_PI * 15 * 15 * 15 / 1000.0, 0.5);
  const LabelImage at_wall = test::make_head_case("tumour_at_ventricle_wall", *atlas_, l).labels;
  // Touching: a tumour voxel has a ventricle voxel as a face neighbour.
  const Mask tumour = mask_of_labels(at_wall, {l.tumour});
  const Mask near_tumour = dilate(tumour, 1.0);
  std::size_t touching = 0;
  for (std::size_t v = 0; v < at_wall.voxels.size(); ++v) touching += near_tumour.voxels[v] && at_wall.voxels[v] == l.ventricles;
  EXPECT_GT(touching, 0u);
}

// A vertex cap the refinement reaches fails with a clear error, not a hang.
TEST(LabelMesherBudgets, RefinementCapFailsWithTheReason) {
  const auto& table = config::default_label_table();
  const LabelImage atlas = atlas_labels_for(load_or_build_default_atlas(atlas_cache()).labels, table);
  MeshingParameters p = coarse(table, atlas);
  p.max_vertices = 2000;
  try {
    mesh_label_image(atlas, p);
    FAIL() << "no error";
  } catch (const ComputeError& e) {
    EXPECT_NE(std::string(e.what()).find("cap of 2000 vertices"), std::string::npos) << e.what();
  }
}

// A budget of zero steps leaves the refined mesh as it is; a small budget is
// hit and said so; both are reproducible.
TEST(LabelMesherBudgets, ExudationStopsAtItsBudget) {
  const auto& table = config::default_label_table();
  const LabelImage atlas = atlas_labels_for(load_or_build_default_atlas(atlas_cache()).labels, table);
  MeshingParameters p = coarse(table, atlas);
  p.exude_steps_per_vertex = 0;
  MeshingStats none;
  mesh_label_image(atlas, p, &none);
  EXPECT_EQ(none.exude_steps, 0u);
  EXPECT_EQ(none.slivers_after, none.slivers_before);
  EXPECT_EQ(none.min_dihedral_after_deg, none.min_dihedral_before_deg);

  p.exude_steps_per_vertex = 0.002;
  MeshingStats a, b;
  const TetMesh ma = mesh_label_image(atlas, p, &a);
  const TetMesh mb = mesh_label_image(atlas, p, &b);
  ASSERT_GT(a.slivers_before, a.exude_budget) << "the case cannot show the budget";
  EXPECT_TRUE(a.exude_budget_hit);
  EXPECT_EQ(a.exude_steps, a.exude_budget);
  EXPECT_LT(a.slivers_after, a.slivers_before);
  ASSERT_EQ(ma.nodes_mm, mb.nodes_mm);
  EXPECT_EQ(ma.tets, mb.tets);
}

}  // namespace
}  // namespace brainshift
