// Pull-back field from a deformed mesh: exactness where the map is affine,
// coverage without cracks, continuity across the mesh boundary, cavities.
#include <gtest/gtest.h>

#include <cmath>
#include <algorithm>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <optional>

#include "box_mesh.h"
#include "core/errors.h"
#include "field/displacement_field.h"
#include "field/metrics.h"
#include "image/image_stats.h"

namespace brainshift {
namespace {

using test::kuhn_box;
using test::oblique_grid;

Eigen::Matrix4d some_affine() {
  Eigen::Matrix4d a = Eigen::Matrix4d::Identity();
  a.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.1, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix() *
                            Eigen::Vector3d(1.05, 0.97, 1.02).asDiagonal();
  a.topRightCorner<3, 1>() = Eigen::Vector3d(3.0, -2.0, 4.5);
  return a;
}

// A 40 mm box mesh centred near the origin, and a grid that extends ~25 mm beyond it.
struct Scene {
  TetMesh mesh = kuhn_box(Eigen::Vector3d(-20, -18, -16), {8, 8, 8}, 5.0);
  Grid3 grid = oblique_grid({70, 64, 36}, Eigen::Vector3d(1.1, 1.2, 2.4), Eigen::Vector3d(-35, -45, -42), 0.3);
};

Eigen::Vector3d field_at(const VectorImage3& f, std::size_t v) { return f.vectors[v].cast<double>(); }

TEST(PullbackField, IdentityGivesZeroEverywhere) {
  Scene s;
  MeshDeformation def;
  def.nonrigid_mm.assign(s.mesh.node_count(), Eigen::Vector3d::Zero());
  FieldStats stats;
  const VectorImage3 u = pullback_field(s.mesh, def, s.grid, FieldParameters{}, &stats);
  EXPECT_GT(stats.covered_voxels, 0u);
  for (const auto& v : u.vectors) ASSERT_LT(v.norm(), 1e-4f);
}

TEST(PullbackField, PureAffineIsExactEverywhere) {
  Scene s;
  MeshDeformation def;
  def.intraop_from_preop = some_affine();
  def.nonrigid_mm.assign(s.mesh.node_count(), Eigen::Vector3d::Zero());
  FieldStats stats;
  const VectorImage3 u = pullback_field(s.mesh, def, s.grid, FieldParameters{}, &stats);
  const Eigen::Matrix4d inv = def.intraop_from_preop.inverse();
  double worst = 0;
  for (int k = 0; k < s.grid.dims[2]; ++k)
    for (int j = 0; j < s.grid.dims[1]; ++j)
      for (int i = 0; i < s.grid.dims[0]; ++i) {
        const Eigen::Vector3d x = s.grid.world_mm(i, j, k);
        const Eigen::Vector3d expected = (inv * x.homogeneous()).head<3>() - x;
        worst = std::max(worst, (field_at(u, s.grid.index(i, j, k)) - expected).norm());
      }
  EXPECT_LT(worst, 1e-4);
  EXPECT_GT(stats.covered_voxels, 1000u);
  EXPECT_EQ(stats.inverted_tets, 0u);
}

// w linear in p makes phi affine, so the pull-back is known in closed form
// inside the deformed box; coverage is checked against the analytic inside set.
TEST(PullbackField, LinearNonrigidReproducedExactlyWithoutCracks) {
  Scene s;
  MeshDeformation def;
  def.intraop_from_preop = some_affine();
  Eigen::Matrix3d b;
  b << 0.04, -0.02, 0.01, 0.03, 0.05, -0.02, -0.01, 0.02, -0.06;
  const Eigen::Vector3d c(1.5, -0.5, 2.0);
  for (const auto& p : s.mesh.nodes_mm) def.nonrigid_mm.push_back(b * p + c);
  FieldStats stats;
  const VectorImage3 u = pullback_field(s.mesh, def, s.grid, FieldParameters{}, &stats);

  const Eigen::Matrix3d total = def.intraop_from_preop.topLeftCorner<3, 3>() + b;
  const Eigen::Vector3d shift = def.intraop_from_preop.topRightCorner<3, 1>() + c;
  const Eigen::Vector3d lo(-20, -18, -16), hi(20, 22, 24);
  std::size_t strictly_inside = 0, loosely_inside = 0;
  double worst = 0;
  for (int k = 0; k < s.grid.dims[2]; ++k)
    for (int j = 0; j < s.grid.dims[1]; ++j)
      for (int i = 0; i < s.grid.dims[0]; ++i) {
        const Eigen::Vector3d x = s.grid.world_mm(i, j, k);
        const Eigen::Vector3d p = total.inverse() * (x - shift);
        const double margin = std::min((p - lo).minCoeff(), (hi - p).minCoeff());
        if (margin > -1e-3) ++loosely_inside;
        if (margin <= 1e-3) continue;
        ++strictly_inside;
        worst = std::max(worst, (field_at(u, s.grid.index(i, j, k)) - (p - x)).norm());
      }
  EXPECT_LT(worst, 1e-4);
  // No cracks: every voxel strictly inside the deformed box is covered.
  EXPECT_GE(stats.covered_voxels, strictly_inside);
  EXPECT_LE(stats.covered_voxels, loosely_inside);
  EXPECT_GT(strictly_inside, 5000u);
}

// A smooth sinking under a "craniotomy": the field must not jump where the
// rasterised part meets the continuation, and must fade to the affine far away.
TEST(PullbackField, ContinuousAcrossMeshBoundaryAndAffineFarAway) {
  Scene s;
  MeshDeformation def;
  const Eigen::Vector3d top(0, 2, 24);
  for (const auto& p : s.mesh.nodes_mm) {
    const double g = std::exp(-(p - top).squaredNorm() / (2 * 12.0 * 12.0));
    def.nonrigid_mm.push_back(Eigen::Vector3d(0, 0, -8.0 * g));
  }
  FieldParameters params;
  FieldStats stats;
  const VectorImage3 u = pullback_field(s.mesh, def, s.grid, params, &stats);

  const Grid3& g = s.grid;
  // Covered voxels: where u differs from zero or the preop point is inside the box.
  // Measure neighbour jumps per unit length along each axis.
  double inside_slope = 0, boundary_slope = 0, far_max = 0;
  const Eigen::Vector3d sp = g.spacing_mm();
  const Eigen::Vector3d lo(-20, -18, -16), hi(20, 22, 24);
  const auto inside = [&](std::size_t v, int i, int j, int k) {
    const Eigen::Vector3d p = g.world_mm(i, j, k) + field_at(u, v);
    return (p - lo).minCoeff() > 0.01 && (hi - p).minCoeff() > 0.01;
  };
  for (int k = 0; k + 1 < g.dims[2]; ++k)
    for (int j = 0; j + 1 < g.dims[1]; ++j)
      for (int i = 0; i + 1 < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        const bool in_v = inside(v, i, j, k);
        const std::array<std::array<int, 3>, 3> nbs{{{i + 1, j, k}, {i, j + 1, k}, {i, j, k + 1}}};
        for (int a = 0; a < 3; ++a) {
          const auto& n = nbs[a];
          const std::size_t w = g.index(n[0], n[1], n[2]);
          const double slope = (field_at(u, v) - field_at(u, w)).norm() / sp[a];
          const bool in_w = inside(w, n[0], n[1], n[2]);
          if (in_v && in_w) inside_slope = std::max(inside_slope, slope);
          if (in_v != in_w) boundary_slope = std::max(boundary_slope, slope);
        }
      }
  for (std::size_t v = 0; v < u.vectors.size(); ++v) {
    const int i = static_cast<int>(v % g.dims[0]);
    const int j = static_cast<int>((v / g.dims[0]) % g.dims[1]);
    const int k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    const Eigen::Vector3d x = g.world_mm(i, j, k);
    const Eigen::Vector3d d = (x.cwiseMax(lo) - x).cwiseMax(x - x.cwiseMin(hi)).cwiseMax(0.0);
    // Beyond the blend distance (plus the 8 mm sinking) only the affine (identity) remains.
    if (d.norm() > params.blend_distance_mm + 9.0) far_max = std::max(far_max, (double)u.vectors[v].norm());
  }
  std::printf("inside slope %.3f, boundary slope %.3f (per mm), far max %.2g mm\n", inside_slope,
              boundary_slope, far_max);
  EXPECT_GT(inside_slope, 0.05);
  // Without continuation a boundary jump of up to 8 mm over ~1 mm would appear.
  EXPECT_LT(boundary_slope, 1.5 * inside_slope);
  EXPECT_LT(far_max, 1e-5);
  EXPECT_GT(stats.blended_voxels, 0u);
}

// Cavities (ventricles) are holes in the mesh: they get the full non-rigid part.
// A whole brain sunk by 12 mm (the remainder the affine leaves of a 22 mm
// sinking), and an intraop outline whose top lies 3 mm above the sunken mesh
// (the fluid's partial volume at the floor of a gap). Over the outline's top
// the field fades from 12 mm to 0 over the 10 mm blend distance: J down to
// 1 - 1.5 * 12 / 10 = -0.8, a fold of the extension, not of the elastic
// solution. The mesh's image (the region the fold gate judges) excludes it
// and holds the exact translation (J = 1).
TEST(PullbackField, TheMeshsImageExcludesTheFadeThatFoldsBeyondIt) {
  Scene s;
  MeshDeformation def;
  def.nonrigid_mm.assign(s.mesh.node_count(), Eigen::Vector3d(0, 0, -12.0));
  FieldStats stats;
  Mask mesh_region;
  const VectorImage3 u = pullback_field(s.mesh, def, s.grid, FieldParameters{}, &stats, &mesh_region);
  ASSERT_TRUE(mesh_region.grid.same_geometry(s.grid));
  EXPECT_EQ(count_nonzero(mesh_region), stats.covered_voxels + stats.cavity_voxels);
  const ImageF det = jacobian_determinant(u);
  const Grid3& g = s.grid;
  const Eigen::Vector3d lo(-20, -18, -28), hi(20, 22, 12 + 3.0);  // the sunken box, its top 3 mm higher
  double min_outline = 1e9, min_mesh = 1e9;
  std::size_t beyond = 0;
  for (int k = 1; k + 1 < g.dims[2]; ++k)
    for (int j = 1; j + 1 < g.dims[1]; ++j)
      for (int i = 1; i + 1 < g.dims[0]; ++i) {
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        if ((x - lo).minCoeff() < 0 || (hi - x).minCoeff() < 0) continue;  // outside the outline
        const std::size_t v = g.index(i, j, k);
        min_outline = std::min(min_outline, static_cast<double>(det.voxels[v]));
        if (mesh_region.voxels[v]) {
          min_mesh = std::min(min_mesh, static_cast<double>(det.voxels[v]));
        } else {
          ++beyond;
        }
      }
  std::printf("outline voxels beyond the mesh %zu, min det over the outline %.3f, over the mesh's image %.3f\n",
              beyond, min_outline, min_mesh);
  EXPECT_GT(beyond, 500u);
  EXPECT_LT(min_outline, 0.0);
  EXPECT_GT(min_mesh, 0.5);
}

TEST(PullbackField, CavityTakesTheSurroundingMotion) {
  Scene s;
  s.mesh = kuhn_box(Eigen::Vector3d(-20, -18, -16), {8, 8, 8}, 5.0, [](int i, int j, int k) {
    return !(i >= 3 && i <= 4 && j >= 3 && j <= 4 && k >= 3 && k <= 4);
  });
  MeshDeformation def;
  const Eigen::Vector3d t(2.0, -1.0, 3.0);
  def.nonrigid_mm.assign(s.mesh.node_count(), t);
  FieldStats stats;
  const VectorImage3 u = pullback_field(s.mesh, def, s.grid, FieldParameters{}, &stats);
  EXPECT_GT(stats.cavity_voxels, 50u);
  // Every voxel whose pull-back lies in the cavity (and the cavity itself moved by t).
  const Eigen::Vector3d cav_lo(-5, -3, -1), cav_hi(5, 7, 9);
  std::size_t checked = 0;
  for (int k = 0; k < s.grid.dims[2]; ++k)
    for (int j = 0; j < s.grid.dims[1]; ++j)
      for (int i = 0; i < s.grid.dims[0]; ++i) {
        const Eigen::Vector3d p = s.grid.world_mm(i, j, k) - t;
        if ((p - cav_lo).minCoeff() < 0.5 || (cav_hi - p).minCoeff() < 0.5) continue;
        ++checked;
        ASSERT_LT((field_at(u, s.grid.index(i, j, k)) + t).norm(), 1e-3);
      }
  EXPECT_GT(checked, 50u);
}

// Preop point p inside the Kuhn box mesh -> phi(p), by locating its tet.
std::optional<Eigen::Vector3d> forward_map(const TetMesh& mesh, const MeshDeformation& def,
                                           const Eigen::Vector3d& p) {
  for (const auto& tet : mesh.tets) {
    Eigen::Matrix3d t;
    t << mesh.nodes_mm[tet[1]] - mesh.nodes_mm[tet[0]], mesh.nodes_mm[tet[2]] - mesh.nodes_mm[tet[0]],
        mesh.nodes_mm[tet[3]] - mesh.nodes_mm[tet[0]];
    const Eigen::Vector3d l = t.inverse() * (p - mesh.nodes_mm[tet[0]]);
    const std::array<double, 4> lambda{1 - l.sum(), l.x(), l.y(), l.z()};
    if (*std::min_element(lambda.begin(), lambda.end()) < -1e-9) continue;
    Eigen::Vector3d q = Eigen::Vector3d::Zero();
    for (int m = 0; m < 4; ++m) q += lambda[m] * def.node_intraop_mm(mesh.nodes_mm[tet[m]], tet[m]);
    return q;
  }
  return std::nullopt;
}

// For a genuinely non-linear (piecewise-linear) deformation the rasterised
// pull-back inverts phi: phi(x + u(x)) = x on covered voxels (the mesh's
// image; an uncovered voxel's continuation may pull back just inside the
// mesh, and is not an inversion).
TEST(PullbackField, InvertsPiecewiseLinearForwardMap) {
  Scene s;
  MeshDeformation def;
  def.intraop_from_preop = some_affine();
  for (const auto& p : s.mesh.nodes_mm) {
    def.nonrigid_mm.push_back(Eigen::Vector3d(1.5 * std::sin(p.y() / 9.0), -2.0 * std::cos(p.z() / 11.0),
                                              -3.0 * std::exp(-p.squaredNorm() / 400.0)));
  }
  FieldStats stats;
  Mask covered;
  const VectorImage3 u = pullback_field(s.mesh, def, s.grid, FieldParameters{}, &stats, &covered);
  EXPECT_EQ(stats.inverted_tets, 0u);
  std::size_t checked = 0;
  double worst = 0;
  for (std::size_t v = 0; v < u.vectors.size(); v += 37) {
    if (!covered.voxels[v]) continue;
    const int i = static_cast<int>(v % s.grid.dims[0]);
    const int j = static_cast<int>((v / s.grid.dims[0]) % s.grid.dims[1]);
    const int k = static_cast<int>(v / (static_cast<std::size_t>(s.grid.dims[0]) * s.grid.dims[1]));
    const Eigen::Vector3d x = s.grid.world_mm(i, j, k);
    const Eigen::Vector3d p = x + field_at(u, v);
    const auto q = forward_map(s.mesh, def, p);
    ASSERT_TRUE(q) << "a covered voxel pulled back outside the mesh";
    ++checked;
    worst = std::max(worst, (*q - x).norm());
  }
  EXPECT_GT(checked, 200u);
  EXPECT_LT(worst, 1e-3);
}

// The continuation reaches the blend distance beyond the brain, and is worked
// on the box it reaches (continue_outside): the field does not depend on how
// far the scan's grid extends beyond that, bit for bit but for the affine's
// rounding. Before, its pyramid fill was aligned to the grid's corner.
TEST(PullbackField, TheFieldDoesNotDependOnHowFarTheGridExtendsBeyondTheBrain) {
  Scene s;
  MeshDeformation def;
  def.intraop_from_preop = some_affine();
  for (const auto& p : s.mesh.nodes_mm)
    def.nonrigid_mm.push_back(Eigen::Vector3d(1.5 * std::sin(p.y() / 9.0), -2.0 * std::cos(p.z() / 11.0),
                                              -3.0 * std::exp(-p.squaredNorm() / 400.0)));
  // The scene's grid padded so that it holds the whole fade (its corners cut
  // it), and that grid padded again by an even number of voxels.
  const auto padded = [&](int pad) {
    Grid3 g = s.grid;
    for (int a = 0; a < 3; ++a) g.dims[a] += 2 * pad;
    g.world_from_voxel.topRightCorner<3, 1>() = s.grid.world_mm(-pad, -pad, -pad);
    return g;
  };
  const int pad = 16, more = 10;
  const Grid3 grid = padded(pad), wider = padded(pad + more);
  FieldStats stats, wider_stats;
  const VectorImage3 u = pullback_field(s.mesh, def, grid, FieldParameters{}, &stats);
  const VectorImage3 w = pullback_field(s.mesh, def, wider, FieldParameters{}, &wider_stats);
  EXPECT_EQ(stats.covered_voxels, wider_stats.covered_voxels);
  EXPECT_EQ(stats.blended_voxels, wider_stats.blended_voxels);
  double worst = 0;
  for (int k = 0; k < grid.dims[2]; ++k)
    for (int j = 0; j < grid.dims[1]; ++j)
      for (int i = 0; i < grid.dims[0]; ++i)
        worst = std::max(worst, (field_at(u, grid.index(i, j, k)) -
                                 field_at(w, wider.index(i + more, j + more, k + more))).norm());
  EXPECT_LT(worst, 1e-4) << "mm";
}

TEST(PullbackField, StatsAsJson) {
  FieldStats stats;
  stats.covered_voxels = 12;
  stats.total_seconds = 0.25;
  const nlohmann::json j = stats;
  EXPECT_EQ(j.at("covered_voxels").get<int>(), 12);
  EXPECT_DOUBLE_EQ(j.at("total_seconds").get<double>(), 0.25);
}

TEST(PullbackField, RejectsInconsistentInput) {
  Scene s;
  MeshDeformation def;
  def.nonrigid_mm.assign(s.mesh.node_count() - 1, Eigen::Vector3d::Zero());
  EXPECT_THROW(pullback_field(s.mesh, def, s.grid, FieldParameters{}), InputError);
  def.nonrigid_mm.assign(s.mesh.node_count(), Eigen::Vector3d::Zero());
  def.intraop_from_preop(0, 0) = 0;
  def.intraop_from_preop(1, 1) = 0;
  EXPECT_THROW(pullback_field(s.mesh, def, s.grid, FieldParameters{}), InputError);
  def.intraop_from_preop = Eigen::Matrix4d::Identity();
  FieldParameters bad;
  bad.blend_distance_mm = 0;
  EXPECT_THROW(pullback_field(s.mesh, def, s.grid, bad), InputError);
  s.mesh.tets.push_back({0, 1, 2, static_cast<int>(s.mesh.node_count())});
  EXPECT_THROW(pullback_field(s.mesh, def, s.grid, FieldParameters{}), InputError);
}

// Brain-sized problem: ~215k tets, 256x256x60 grid at 0.94x0.94x2.5 mm.
TEST(PullbackField, BrainSizedTiming) {
  const TetMesh mesh = kuhn_box(Eigen::Vector3d(-67, -84, -59), {32, 40, 28}, 4.2);
  ASSERT_EQ(mesh.tet_count(), 32u * 40 * 28 * 6);
  const Grid3 grid = oblique_grid({256, 256, 60}, Eigen::Vector3d(0.94, 0.94, 2.5),
                                  Eigen::Vector3d(-120, -120, -75), 0.05);
  MeshDeformation def;
  def.intraop_from_preop.topRightCorner<3, 1>() = Eigen::Vector3d(1, -2, 0.5);
  const Eigen::Vector3d top(20, 0, 59);
  for (const auto& p : mesh.nodes_mm) {
    const double g = std::exp(-(p - top).squaredNorm() / (2 * 30.0 * 30.0));
    def.nonrigid_mm.push_back(Eigen::Vector3d(0, 0, -12.0 * g));
  }
  FieldStats stats;
  const VectorImage3 u = pullback_field(mesh, def, grid, FieldParameters{}, &stats);
  std::printf("covered %zu cavity %zu blended %zu: rasterise %.3f s, fill %.3f s, total %.3f s\n",
              stats.covered_voxels, stats.cavity_voxels, stats.blended_voxels, stats.rasterise_seconds,
              stats.fill_seconds, stats.total_seconds);
  EXPECT_EQ(u.vectors.size(), grid.voxel_count());
  EXPECT_GT(stats.covered_voxels, 1000000u);
  // The time is printed above; speed goals live in the benchmarks.
}

}  // namespace
}  // namespace brainshift
