// Carrying models with a mesh deformation: exact for affine maps everywhere and
// for nodal residuals that are linear in space inside the mesh (linear
// interpolation in tets reproduces linear functions).
#include <gtest/gtest.h>

#include <chrono>
#include <random>

#include "core/errors.h"
#include "models/carry.h"

namespace brainshift {
namespace {

// A box of n^3 cubes of side h starting at origin, each cube split into the
// six Kuhn tets, all positively oriented.
TetMesh kuhn_box(int n, double h, const Eigen::Vector3d& origin) {
  TetMesh m;
  const int np = n + 1;
  auto id = [np](int i, int j, int k) { return i + np * (j + np * k); };
  for (int k = 0; k < np; ++k)
    for (int j = 0; j < np; ++j)
      for (int i = 0; i < np; ++i) m.nodes_mm.push_back(origin + h * Eigen::Vector3d(i, j, k));
  const int perms[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i)
        for (const auto& p : perms) {
          std::array<int, 3> c{i, j, k};
          std::array<int, 4> tet;
          tet[0] = id(c[0], c[1], c[2]);
          ++c[p[0]];
          tet[1] = id(c[0], c[1], c[2]);
          ++c[p[1]];
          tet[2] = id(c[0], c[1], c[2]);
          tet[3] = id(i + 1, j + 1, k + 1);
          m.tets.push_back(tet);
          if (tet_volume_mm3(m, m.tets.size() - 1) < 0) std::swap(m.tets.back()[2], m.tets.back()[3]);
          m.tet_labels.push_back(1);
        }
  return m;
}

Eigen::Matrix4d some_affine() {
  Eigen::Matrix4d a = Eigen::Matrix4d::Identity();
  a.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.1, Eigen::Vector3d(0.3, -1, 0.5).normalized()).toRotationMatrix() *
                            Eigen::Vector3d(1.02, 0.97, 1.05).asDiagonal();
  a.topRightCorner<3, 1>() = Eigen::Vector3d(2.5, -4, 1);
  return a;
}

TriSurface random_points(std::size_t count, const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  TriSurface s;
  for (std::size_t v = 0; v < count; ++v)
    s.vertices_mm.push_back(lo + Eigen::Vector3d(u(rng), u(rng), u(rng)).cwiseProduct(hi - lo));
  for (std::size_t v = 0; v + 2 < count; v += 3)
    s.triangles.push_back({static_cast<int>(v), static_cast<int>(v + 1), static_cast<int>(v + 2)});
  return s;
}

TEST(Carry, AffineOnlyEqualsTheAffineInsideAndOutside) {
  const TetMesh mesh = kuhn_box(6, 5.0, Eigen::Vector3d(-15, -15, -15));
  // Some points lie up to 5 mm outside the 30 mm box.
  const TriSurface model = random_points(3000, Eigen::Vector3d::Constant(-20), Eigen::Vector3d::Constant(20), 1);
  const ModelBinding b = bind_to_mesh(model, mesh);
  EXPECT_GT(b.vertices_outside, 0u);
  MeshDeformation d;
  d.intraop_from_preop = some_affine();
  d.nonrigid_mm.assign(mesh.node_count(), Eigen::Vector3d::Zero());
  const TriSurface moved = carry(model, b, d);
  ASSERT_EQ(moved.vertices_mm.size(), model.vertices_mm.size());
  EXPECT_EQ(moved.triangles, model.triangles);
  for (std::size_t v = 0; v < model.vertices_mm.size(); ++v)
    EXPECT_LT((moved.vertices_mm[v] - d.apply_affine(model.vertices_mm[v])).norm(), 1e-9);
}

TEST(Carry, LinearResidualIsExactInsideTheMesh) {
  const TetMesh mesh = kuhn_box(5, 4.0, Eigen::Vector3d(10, -30, 5));
  Eigen::Matrix3d grad;
  grad << 0.05, -0.02, 0.01, 0.03, 0.04, -0.06, -0.01, 0.02, 0.08;
  const Eigen::Vector3d offset(1.5, -0.5, 3);
  auto residual = [&](const Eigen::Vector3d& p) -> Eigen::Vector3d { return grad * p + offset; };
  MeshDeformation d;
  d.intraop_from_preop = some_affine();
  for (const auto& p : mesh.nodes_mm) d.nonrigid_mm.push_back(residual(p));

  const TriSurface model = random_points(5000, Eigen::Vector3d(10, -30, 5), Eigen::Vector3d(30, -10, 25), 2);
  const ModelBinding b = bind_to_mesh(model, mesh);
  EXPECT_EQ(b.vertices_outside, 0u);
  const TriSurface moved = carry(model, b, d);
  for (std::size_t v = 0; v < model.vertices_mm.size(); ++v) {
    const Eigen::Vector3d& p = model.vertices_mm[v];
    EXPECT_LT((moved.vertices_mm[v] - (d.apply_affine(p) + residual(p))).norm(), 1e-9);
  }
}

TEST(Carry, OutsideVerticesTakeTheResidualOfTheClosestMeshPoint) {
  const TetMesh mesh = kuhn_box(4, 5.0, Eigen::Vector3d::Zero());  // box [0,20]^3
  MeshDeformation d;
  for (const auto& p : mesh.nodes_mm) d.nonrigid_mm.push_back(Eigen::Vector3d(0.1 * p.x(), 0.2 * p.y(), 0.3 * p.z()));
  TriSurface model;
  model.vertices_mm = {Eigen::Vector3d(23, 7, 11),    // beyond the x = 20 face: closest (20, 7, 11)
                       Eigen::Vector3d(-2, -3, 30),   // beyond an edge/corner region: closest (0, 0, 20)
                       Eigen::Vector3d(10, 10, 10)};  // inside
  const ModelBinding b = bind_to_mesh(model, mesh);
  EXPECT_EQ(b.vertices_outside, 2u);
  EXPECT_NEAR(b.max_distance_outside_mm, std::sqrt(4.0 + 9.0 + 100.0), 1e-9);
  const TriSurface moved = carry(model, b, d);
  EXPECT_LT((moved.vertices_mm[0] - (model.vertices_mm[0] + Eigen::Vector3d(2.0, 1.4, 3.3))).norm(), 1e-9);
  EXPECT_LT((moved.vertices_mm[1] - (model.vertices_mm[1] + Eigen::Vector3d(0.0, 0.0, 6.0))).norm(), 1e-9);
  EXPECT_LT((moved.vertices_mm[2] - Eigen::Vector3d(11, 12, 13)).norm(), 1e-9);
}

TEST(Carry, RejectsMismatchedInputs) {
  const TetMesh mesh = kuhn_box(2, 1.0, Eigen::Vector3d::Zero());
  const TriSurface model = random_points(30, Eigen::Vector3d::Zero(), Eigen::Vector3d::Constant(2), 3);
  const ModelBinding b = bind_to_mesh(model, mesh);
  MeshDeformation d;
  d.nonrigid_mm.assign(mesh.node_count() - 1, Eigen::Vector3d::Zero());
  EXPECT_THROW(carry(model, b, d), InputError);
  d.nonrigid_mm.assign(mesh.node_count(), Eigen::Vector3d::Zero());
  TriSurface other = model;
  other.vertices_mm.pop_back();
  EXPECT_THROW(carry(other, b, d), InputError);
  EXPECT_THROW(bind_to_mesh(model, TetMesh{}), InputError);
}

TEST(Carry, PerScanGatherIsFast) {
  const TetMesh mesh = kuhn_box(30, 4.0, Eigen::Vector3d::Zero());  // 162k tets
  const TriSurface model = random_points(100000, Eigen::Vector3d::Constant(1), Eigen::Vector3d::Constant(119), 4);
  const auto t0 = std::chrono::steady_clock::now();
  const ModelBinding b = bind_to_mesh(model, mesh);
  const auto t1 = std::chrono::steady_clock::now();
  MeshDeformation d;
  d.intraop_from_preop = some_affine();
  d.nonrigid_mm.assign(mesh.node_count(), Eigen::Vector3d(1, 2, 3));
  const TriSurface moved = carry(model, b, d);
  const auto t2 = std::chrono::steady_clock::now();
  const double bind_ms = std::chrono::duration<double, std::milli>(t1 - t0).count();
  const double carry_ms = std::chrono::duration<double, std::milli>(t2 - t1).count();
  std::printf("bind %.1f ms, carry %.2f ms for 100k vertices, %zu tets\n", bind_ms, carry_ms, mesh.tet_count());
  // The time is printed above; speed goals live in the benchmarks.
  EXPECT_LT((moved.vertices_mm[0] - d.apply_affine(model.vertices_mm[0]) - Eigen::Vector3d(1, 2, 3)).norm(), 1e-9);
}

}  // namespace
}  // namespace brainshift
