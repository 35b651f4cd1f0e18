// Surface models against analytic shapes: a voxelised sphere must give the
// sphere's area and volume, a closed consistently oriented surface with
// outward normals, whatever the orientation of the voxel grid.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "core/errors.h"
#include "mesh/vtk_io.h"
#include "models/surface_models.h"

namespace brainshift {
namespace {

// A ball of radius_mm centred at centre_mm (world), on a grid with the given affine.
LabelImage ball_labels(const Eigen::Matrix4d& world_from_voxel, int n, const Eigen::Vector3d& centre_mm,
                       double radius_mm, std::uint16_t label) {
  Grid3 g;
  g.dims = {n, n, n};
  g.world_from_voxel = world_from_voxel;
  LabelImage img(g, 0);
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i)
        if ((g.world_mm(i, j, k) - centre_mm).norm() <= radius_mm) img.at(i, j, k) = label;
  return img;
}

Eigen::Matrix4d scaled(double s, const Eigen::Vector3d& origin) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topLeftCorner<3, 3>() *= s;
  m.topRightCorner<3, 1>() = origin;
  return m;
}

void expect_sphere(const TriSurface& s, double r, const Eigen::Vector3d& centre) {
  ASSERT_FALSE(s.triangles.empty());
  EXPECT_TRUE(is_closed_oriented_manifold(s));
  const double area = 4 * std::numbers::pi * r * r, volume = 4.0 / 3.0 * std::numbers::pi * r * r * r;
  EXPECT_NEAR(surface_area_mm2(s), area, 0.03 * area);
  EXPECT_NEAR(enclosed_volume_mm3(s), volume, 0.03 * volume);  // positive: outward normals
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& v : s.vertices_mm) mean += v;
  mean /= static_cast<double>(s.vertices_mm.size());
  EXPECT_LT((mean - centre).norm(), 0.2);
  // Vertices lie close to the sphere (voxelisation + smoothing error).
  for (const auto& v : s.vertices_mm) EXPECT_NEAR((v - centre).norm(), r, 0.6);
}

TEST(SurfaceModel, SphereAreaVolumeAndTopology) {
  const Eigen::Vector3d centre(3.3, -10.2, 20.7);
  const double r = 12.0;
  const auto labels = ball_labels(scaled(1.0, centre - Eigen::Vector3d::Constant(20)), 40, centre, r, 4);
  expect_sphere(surface_model(labels, std::uint16_t{4}), r, centre);
}

TEST(SurfaceModel, ShortEdgeCollapseKeepsShapeAndTopology) {
  const Eigen::Vector3d centre(0.3, 0.1, -0.2);
  const auto labels = ball_labels(scaled(1.0, centre - Eigen::Vector3d::Constant(20)), 40, centre, 14, 1);
  ModelParameters raw;
  raw.min_edge_fraction = 0;
  const TriSurface dense = surface_model(labels, std::uint16_t{1}, raw);
  const TriSurface lean = surface_model(labels, std::uint16_t{1});
  EXPECT_TRUE(is_closed_oriented_manifold(lean));
  EXPECT_LT(lean.triangles.size(), 0.75 * dense.triangles.size());
  EXPECT_NEAR(enclosed_volume_mm3(lean), enclosed_volume_mm3(dense), 0.005 * enclosed_volume_mm3(dense));
  // Same genus (sphere): V - E + F = 2.
  const long v = static_cast<long>(lean.vertices_mm.size()), f = static_cast<long>(lean.triangles.size());
  EXPECT_EQ(v - 3 * f / 2 + f, 2);
}

TEST(SurfaceModel, FlippedObliqueAffineKeepsOutwardNormals) {
  const Eigen::Vector3d centre(-5, 7, 1);
  const double r = 10.0;
  Eigen::Matrix4d w = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d rot = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  w.topLeftCorner<3, 3>() = rot * Eigen::Vector3d(-0.8, 0.8, 0.8).asDiagonal();  // det < 0
  ASSERT_LT((w.topLeftCorner<3, 3>().determinant()), 0);
  // Place voxel (20,20,20) at the centre.
  w.topRightCorner<3, 1>() = centre - w.topLeftCorner<3, 3>() * Eigen::Vector3d::Constant(20);
  const auto labels = ball_labels(w, 40, centre, r, 1);
  expect_sphere(surface_model(labels, std::uint16_t{1}), r, centre);
}

// Every .vtp carries per-vertex normals that VTK and 3D Slicer shade with:
// unit length, outward (radial on a ball, also through a handedness-flipping
// oblique grid), in RAS like the points, and read back as written.
TEST(SurfaceModel, VtpCarriesOutwardUnitNormals) {
  const Eigen::Vector3d centre(-5, 7, 1);
  const double r = 10.0;
  Eigen::Matrix4d w = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d rot = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  w.topLeftCorner<3, 3>() = rot * Eigen::Vector3d(-0.8, 0.8, 0.8).asDiagonal();
  w.topRightCorner<3, 1>() = centre - w.topLeftCorner<3, 3>() * Eigen::Vector3d::Constant(20);
  const TriSurface s = surface_model(ball_labels(w, 40, centre, r, 1), std::uint16_t{1});
  const std::string xml = vtp_bytes(s);
  EXPECT_NE(xml.find("<PointData Normals=\"Normals\">"), std::string::npos);
  const std::vector<Eigen::Vector3d> normals = read_vtp_normals(xml, "ball.vtp");
  ASSERT_EQ(normals.size(), s.vertices_mm.size());
  double worst_cos = 1;
  for (std::size_t v = 0; v < normals.size(); ++v) {
    EXPECT_NEAR(normals[v].norm(), 1.0, 2e-4) << v;  // 4 decimals per component
    worst_cos = std::min(worst_cos, normals[v].dot((s.vertices_mm[v] - centre).normalized()));
  }
  // A smoothed voxel sphere: every normal within ~25 degrees of the radius.
  EXPECT_GT(worst_cos, 0.9);
  // As written: the area-weighted vertex normals, to the 4 decimals of the text.
  const std::vector<Eigen::Vector3d> exact = vertex_normals(s);
  for (std::size_t v = 0; v < normals.size(); ++v) EXPECT_LT((normals[v] - exact[v]).cwiseAbs().maxCoeff(), 0.5e-4 + 1e-12);
  // An LPS file's normals come back in RAS, like its points.
  std::string lps = xml;
  lps.replace(lps.find("82 65 83 0"), 10, "76 80 83 0");
  const auto from_lps = read_vtp_normals(lps, "lps.vtp");
  ASSERT_EQ(from_lps.size(), normals.size());
  EXPECT_EQ(from_lps[0], Eigen::Vector3d(-normals[0].x(), -normals[0].y(), normals[0].z()));
  // The writer owns the name: a caller's "Normals" array would be a second one.
  SurfaceAttributes clash;
  clash.vectors.push_back({"Normals", s.vertices_mm});
  EXPECT_THROW(vtp_bytes(s, clash), InputError);
}

TEST(SurfaceModel, AnisotropicVoxels) {
  Grid3 g;
  g.dims = {48, 48, 20};
  g.world_from_voxel = Eigen::Vector4d(0.9375, 0.9375, 2.5, 1).asDiagonal();
  LabelImage img(g, 0);
  const Eigen::Vector3d centre = g.world_mm(23.5, 23.5, 9.5);
  const double r = 15;
  for (int k = 0; k < 20; ++k)
    for (int j = 0; j < 48; ++j)
      for (int i = 0; i < 48; ++i)
        if ((g.world_mm(i, j, k) - centre).norm() <= r) img.at(i, j, k) = 2;
  const TriSurface s = surface_model(img, std::uint16_t{2});
  EXPECT_TRUE(is_closed_oriented_manifold(s));
  const double volume = 4.0 / 3.0 * std::numbers::pi * r * r * r;
  // 2.5 mm slices: the voxelised volume itself is only good to a few percent.
  EXPECT_NEAR(enclosed_volume_mm3(s), volume, 0.05 * volume);
}

TEST(SurfaceModel, TorusIsOneClosedSurfaceWithHole) {
  Grid3 g;
  g.dims = {50, 50, 20};
  LabelImage img(g, 0);
  const double big = 15, small = 5;
  for (int k = 0; k < 20; ++k)
    for (int j = 0; j < 50; ++j)
      for (int i = 0; i < 50; ++i) {
        const double x = i - 24.5, y = j - 24.5, z = k - 9.5;
        const double q = std::hypot(x, y) - big;
        if (q * q + z * z <= small * small) img.at(i, j, k) = 3;
      }
  const TriSurface s = surface_model(img, std::uint16_t{3});
  EXPECT_TRUE(is_closed_oriented_manifold(s));
  // Euler characteristic of a torus is 0: V - E + F with E = 3F/2.
  const long v = static_cast<long>(s.vertices_mm.size()), f = static_cast<long>(s.triangles.size());
  EXPECT_EQ(v - 3 * f / 2 + f, 0);
  const double volume = 2 * std::numbers::pi * std::numbers::pi * big * small * small;
  EXPECT_NEAR(enclosed_volume_mm3(s), volume, 0.04 * volume);
}

TEST(SurfaceModel, RandomBlobsAreAlwaysClosedManifolds) {
  // Binary noise is the worst case for contouring ambiguity.
  Grid3 g;
  g.dims = {16, 16, 16};
  LabelImage img(g, 0);
  unsigned state = 12345;
  for (auto& v : img.voxels) {
    state = state * 1664525u + 1013904223u;
    v = (state >> 28) < 7 ? 1 : 0;
  }
  ModelParameters p;
  p.presmooth_sigma_mm = 0;  // contour the raw binary mask
  const TriSurface s = surface_model(img, std::uint16_t{1}, p);
  EXPECT_TRUE(is_closed_oriented_manifold(s));
  EXPECT_GT(enclosed_volume_mm3(s), 0);
}

TEST(SurfaceModel, StructureTableSkipsAbsentStructures) {
  Grid3 g;
  g.dims = {40, 40, 40};
  LabelImage img(g, 0);
  for (int k = 0; k < 40; ++k)
    for (int j = 0; j < 40; ++j)
      for (int i = 0; i < 40; ++i) {
        const double r = std::sqrt((i - 19.5) * (i - 19.5) + (j - 19.5) * (j - 19.5) + (k - 19.5) * (k - 19.5));
        if (r < 15) img.at(i, j, k) = r < 5 ? 2 : 1;
      }
  const auto models = structure_models(img, {{"brain", {1, 2}}, {"ventricles", {2}}, {"tumor", {4}}});
  ASSERT_EQ(models.size(), 2u);
  const auto& brain = models.at("brain");
  const auto& vent = models.at("ventricles");
  // The brain model is the outer surface only (the ventricle is inside it).
  EXPECT_NEAR(enclosed_volume_mm3(brain), 4.0 / 3.0 * std::numbers::pi * 15 * 15 * 15, 0.04 * 14137);
  EXPECT_NEAR(enclosed_volume_mm3(vent), 4.0 / 3.0 * std::numbers::pi * 125, 0.1 * 524);
  EXPECT_FALSE(models.contains("tumor"));
}

TEST(SurfaceModel, RejectsBadInput) {
  EXPECT_THROW(surface_model(LabelImage{}, std::uint16_t{1}), InputError);
  Grid3 g;
  g.dims = {4, 4, 4};
  ModelParameters shrinking;
  shrinking.taubin_mu = -0.1;
  EXPECT_THROW(surface_model(LabelImage(g, 1), std::uint16_t{1}, shrinking), InputError);
  EXPECT_TRUE(surface_model(LabelImage(g, 0), std::uint16_t{1}).triangles.empty());
}

}  // namespace
}  // namespace brainshift
