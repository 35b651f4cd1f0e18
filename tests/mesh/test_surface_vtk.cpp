// Fast tests of the CGAL-free parts: assembly, quality, surfaces, VTK I/O.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <regex>
#include <set>

#include "core/errors.h"
#include "mesh/mesh_assembly.h"
#include "mesh/mesh_quality.h"
#include "mesh/surface_extraction.h"
#include "mesh/vtk_io.h"
#include "temp_dir.h"

namespace brainshift {
namespace {

// Unit cube [0,s]^3 split into 6 tets around the 0-6 diagonal (Kuhn split),
// given with mixed orientations as a raw mesh, its 12 boundary facets marked.
RawTetMesh raw_cube(double s) {
  RawTetMesh raw;
  for (int n = 0; n < 8; ++n) raw.nodes_mm.emplace_back(s * (n & 1), s * ((n >> 1) & 1), s * ((n >> 2) & 1));
  raw.nodes_mm.emplace_back(9, 9, 9);  // unused node: must be removed
  // Paths 0 -> 7 through the cube's corners (x=1,y=2,z=4 bits).
  const int paths[6][2] = {{1, 3}, {1, 5}, {2, 3}, {2, 6}, {4, 5}, {4, 6}};
  for (const auto& p : paths) raw.tets.push_back({0, p[0], p[1], 7});
  return raw;
}

// Marks every tet face not shared with another tet as outer boundary.
void mark_boundary(RawTetMesh& raw) {
  for (std::size_t t = 0; t < raw.tets.size(); ++t)
    for (int f = 0; f < 4; ++f) {
      std::set<int> face;
      for (int a = 0; a < 4; ++a)
        if (a != f) face.insert(raw.tets[t][a]);
      int shared = 0;
      for (std::size_t u = 0; u < raw.tets.size(); ++u) {
        if (u == t) continue;
        const std::set<int> other(raw.tets[u].begin(), raw.tets[u].end());
        shared += std::includes(other.begin(), other.end(), face.begin(), face.end());
      }
      if (!shared) raw.boundary.push_back({static_cast<int>(t), f, 0});
    }
}

LabelImage cube_labels(double s) {
  Grid3 g;
  g.dims = {3, 3, 3};
  g.world_from_voxel.topLeftCorner<3, 3>() *= s / 2;
  LabelImage img(g, 1);
  return img;
}

TetMesh cube_mesh(double s = 2.0) {
  RawTetMesh raw = raw_cube(s);
  mark_boundary(raw);
  AssemblyOptions o;
  return assemble_tet_mesh(raw, cube_labels(s), o);
}

TEST(MeshAssembly, CubeIsOrientedCompactAndClosed) {
  const TetMesh m = cube_mesh(2.0);
  ASSERT_EQ(m.node_count(), 8u);  // the unused node is gone
  ASSERT_EQ(m.tet_count(), 6u);
  ASSERT_EQ(m.boundary_faces.size(), 12u);
  for (std::size_t t = 0; t < m.tet_count(); ++t) EXPECT_NEAR(tet_volume_mm3(m, t), 8.0 / 6.0, 1e-12);
  const MeshQuality q = measure_quality(m);
  EXPECT_EQ(q.inverted_tets, 0u);
  EXPECT_EQ(q.degenerate_tets, 0u);
  EXPECT_NEAR(q.total_volume_mm3, 8.0, 1e-12);
  const TriSurface outer = extract_boundary_surface(m, 0);
  EXPECT_NEAR(enclosed_volume_mm3(outer), 8.0, 1e-12);  // outward-facing and closed
  EXPECT_EQ(count_connected_components(outer), 1u);
  EXPECT_EQ(boundary_nodes(m).size(), 8u);
  // Tets are sorted by their smallest node.
  for (std::size_t t = 1; t < m.tet_count(); ++t)
    EXPECT_LE(*std::min_element(m.tets[t - 1].begin(), m.tets[t - 1].end()),
              *std::min_element(m.tets[t].begin(), m.tets[t].end()));
}

TEST(MeshAssembly, TetLabelComesFromNearestVoxelAndDefaultsForBackground) {
  // Label 5 on the voxel slab i = 2 (x >= 1.5 mm). Of the six Kuhn tets of a
  // 2 mm cube only the two through corner 1 = (2,0,0) have centroid x = 1.5.
  LabelImage labels = cube_labels(2.0);
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j) labels.at(2, j, k) = 5;
  RawTetMesh with_faces = raw_cube(2.0);
  const TetMesh m = assemble_tet_mesh(with_faces, labels, {});
  EXPECT_EQ(std::count(m.tet_labels.begin(), m.tet_labels.end(), 5), 2);
  EXPECT_EQ(std::count(m.tet_labels.begin(), m.tet_labels.end(), 1), 4);
  // Background (0) and cavity labels fall back to the default tissue label.
  RawTetMesh raw = raw_cube(2.0);
  LabelImage zero(labels.grid, 0);
  AssemblyOptions o;
  o.default_tissue_label = 3;
  for (int l : assemble_tet_mesh(raw, zero, o).tet_labels) EXPECT_EQ(l, 3);
  LabelImage cavity(labels.grid, 2);
  o.cavity_labels = {2};
  for (int l : assemble_tet_mesh(raw, cavity, o).tet_labels) EXPECT_EQ(l, 3);
}

TEST(MeshAssembly, DegenerateTetIsDropped) {
  RawTetMesh raw = raw_cube(1.0);
  raw.nodes_mm.emplace_back(0.5, 0.5, 0.0);  // flat tet: all four nodes in z = 0
  raw.tets.push_back({0, 1, 2, static_cast<int>(raw.nodes_mm.size()) - 1});
  AssemblyReport report;
  const TetMesh m = assemble_tet_mesh(raw, cube_labels(1.0), {}, &report);
  EXPECT_EQ(report.dropped_degenerate, 1u);
  EXPECT_EQ(m.tet_count(), 6u);
  EXPECT_EQ(m.node_count(), 8u);
}

TEST(MeshAssembly, KeepsOnlyTheLargestPieceWhenAsked) {
  // A 2 mm cube and, 10 mm away, a 1 mm cube: the small one is an island.
  RawTetMesh raw = raw_cube(2.0);
  mark_boundary(raw);
  const RawTetMesh small = raw_cube(1.0);
  const int offset = static_cast<int>(raw.nodes_mm.size());
  for (const auto& x : small.nodes_mm) raw.nodes_mm.push_back(x + Eigen::Vector3d(10, 0, 0));
  for (auto t : small.tets) {
    for (int& n : t) n += offset;
    raw.tets.push_back(t);
  }
  AssemblyOptions o;
  EXPECT_EQ(assemble_tet_mesh(raw, cube_labels(2.0), o).tet_count(), 12u);
  o.keep_largest_component = true;
  AssemblyReport report;
  const TetMesh m = assemble_tet_mesh(raw, cube_labels(2.0), o, &report);
  EXPECT_EQ(report.dropped_island_tets, 6u);
  EXPECT_EQ(m.tet_count(), 6u);
  EXPECT_EQ(m.node_count(), 8u);
  EXPECT_NEAR(measure_quality(m).total_volume_mm3, 8.0, 1e-12);
  EXPECT_EQ(m.boundary_faces.size(), 12u);
}

TEST(MortonOrder, IsAPermutationThatVisitsOctantsContiguously) {
  std::vector<Eigen::Vector3d> pts;
  for (int k = 3; k >= 0; --k)
    for (int j = 3; j >= 0; --j)
      for (int i = 3; i >= 0; --i) pts.emplace_back(i, j, k);
  const auto order = morton_order(pts);
  ASSERT_EQ(order.size(), 64u);
  EXPECT_EQ(std::set<int>(order.begin(), order.end()).size(), 64u);
  // Each run of 8 is one 2x2x2 block.
  for (int block = 0; block < 8; ++block) {
    Eigen::Vector3d lo = pts[order[8 * block]], hi = lo;
    for (int n = 0; n < 8; ++n) lo = lo.cwiseMin(pts[order[8 * block + n]]), hi = hi.cwiseMax(pts[order[8 * block + n]]);
    EXPECT_EQ((hi - lo), Eigen::Vector3d(1, 1, 1));
  }
  EXPECT_EQ(pts[order[0]], Eigen::Vector3d(0, 0, 0));
}

TEST(MeshQuality, RegularTetAndInvertedTet) {
  TetMesh m;
  m.nodes_mm = {{1, 1, 1}, {1, -1, -1}, {-1, 1, -1}, {-1, -1, 1}};
  m.tets = {{0, 1, 2, 3}};
  if (tet_volume_mm3(m, 0) < 0) std::swap(m.tets[0][2], m.tets[0][3]);
  m.tet_labels = {1};
  MeshQuality q = measure_quality(m);
  const double regular_dihedral = std::acos(1.0 / 3.0) * 180 / M_PI;  // 70.53 deg
  EXPECT_NEAR(q.min_dihedral_deg, regular_dihedral, 1e-9);
  EXPECT_NEAR(q.max_dihedral_deg, regular_dihedral, 1e-9);
  EXPECT_NEAR(q.max_radius_edge_ratio, std::sqrt(6.0) / 4.0, 1e-12);
  EXPECT_NEAR(q.total_volume_mm3, 8.0 / 3.0, 1e-12);  // edge 2*sqrt(2): a^3/(6 sqrt 2)
  EXPECT_EQ(q.inverted_tets, 0u);
  std::swap(m.tets[0][0], m.tets[0][1]);
  q = measure_quality(m);
  EXPECT_EQ(q.inverted_tets, 1u);
  EXPECT_LT(q.min_volume_mm3, 0);
}

TEST(VtkIo, VtpRoundTripsExactly) {
  const TetMesh m = cube_mesh(1.0 / 3.0);  // non-representable decimals
  const TriSurface s = extract_boundary_surface(m, kAnyBoundary);
  SurfaceAttributes attrs;
  attrs.scalars.push_back({"distance_mm", std::vector<double>(s.vertices_mm.size(), 0.25)});
  attrs.vectors.push_back({"displacement_mm", s.vertices_mm});
  const test::TempDir dir("vtk");
  const auto path = dir / "surface.vtp";
  write_vtp(path, s, attrs);
  const TriSurface back = read_vtp(path);
  ASSERT_EQ(back.vertices_mm.size(), s.vertices_mm.size());
  for (std::size_t v = 0; v < s.vertices_mm.size(); ++v) EXPECT_EQ(back.vertices_mm[v], s.vertices_mm[v]);
  EXPECT_EQ(back.triangles, s.triangles);
  EXPECT_EQ(back.mesh_node, s.mesh_node);
  EXPECT_EQ(read_vtp_bytes(vtp_bytes(s)).triangles, s.triangles);
}

// 3D Slicer takes a model without SPACE as LPS and mirrors it in x and y: every
// file must say RAS, in the field-data form VTK's own XML reader understands
// (a String array of character codes ending in 0).
TEST(VtkIo, EveryFileNamesItsFrame) {
  const TetMesh m = cube_mesh(1.0);
  const TriSurface s = extract_boundary_surface(m, kAnyBoundary);
  const std::string field =
      "<FieldData>\n<Array type=\"String\" Name=\"SPACE\" NumberOfTuples=\"1\" format=\"ascii\">\n82 65 83 0\n</Array>\n</FieldData>\n";
  const std::string vtp = vtp_bytes(s), vtu = vtu_bytes(m);
  EXPECT_NE(vtp.find("<PolyData>\n" + field + "<Piece"), std::string::npos) << vtp.substr(0, 300);
  EXPECT_NE(vtu.find("<UnstructuredGrid>\n" + field + "<Piece"), std::string::npos) << vtu.substr(0, 300);
  EXPECT_EQ(vtk_space(vtp), "RAS");
  EXPECT_EQ(vtk_space(vtu), "RAS");
  const test::TempDir dir("vtk");
  write_vtp(dir / "space.vtp", s);
  std::ifstream in(dir / "space.vtp");
  const std::string on_disk((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_EQ(vtk_space(on_disk), "RAS");
}

// A closed cube: each corner's normal is the area-weighted mean of its three
// faces' normals, so it points outward, within 55 degrees of the diagonal.
TEST(VtkIo, VtpNormalsAreUnitAndOutward) {
  const TetMesh m = cube_mesh(2.0);
  const TriSurface s = extract_boundary_surface(m, kAnyBoundary);
  const auto normals = read_vtp_normals(vtp_bytes(s));
  ASSERT_EQ(normals.size(), s.vertices_mm.size());
  const Eigen::Vector3d centre(1, 1, 1);
  for (std::size_t v = 0; v < normals.size(); ++v) {
    EXPECT_NEAR(normals[v].norm(), 1.0, 2e-4);  // 4 decimals per component
    const Eigen::Vector3d radial = s.vertices_mm[v] - centre;
    EXPECT_GT(normals[v].dot(radial), 0.5 * radial.norm()) << v;
  }
}

TEST(VtkIo, ReadsLpsModelsIntoRas) {
  TriSurface s;
  s.vertices_mm = {{10, 20, 30}, {-11, 21, 31}, {12, -22, 32}};
  s.triangles = {{0, 1, 2}};
  std::string lps = vtp_bytes(s);
  lps.replace(lps.find("82 65 83 0"), 10, "76 80 83 0");  // "LPS"
  ASSERT_EQ(vtk_space(lps), "LPS");
  const TriSurface back = read_vtp_bytes(lps);
  for (std::size_t v = 0; v < 3; ++v)
    EXPECT_EQ(back.vertices_mm[v], Eigen::Vector3d(-s.vertices_mm[v].x(), -s.vertices_mm[v].y(), s.vertices_mm[v].z()));
  std::string unknown = vtp_bytes(s);
  unknown.replace(unknown.find("82 65 83 0"), 10, "88 89 90 0");  // "XYZ"
  EXPECT_THROW(read_vtp_bytes(unknown, "x.vtp"), InputError);
}

TEST(VtkIo, VtpRejectsBadInput) {
  EXPECT_THROW(read_vtp_bytes("<VTKFile type=\"UnstructuredGrid\"/>", "x.vtp"), InputError);
  TriSurface s;
  s.vertices_mm = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  s.triangles = {{0, 1, 2}};
  std::string bytes = vtp_bytes(s);
  bytes.replace(bytes.find("0 1 2\n"), 6, "0 1 5\n");  // vertex out of range
  EXPECT_THROW(read_vtp_bytes(bytes, "x.vtp"), InputError);
  EXPECT_THROW(read_vtp("/nonexistent/dir/x.vtp"), InputError);
  SurfaceAttributes wrong;
  wrong.scalars.push_back({"too_short", {1.0}});
  EXPECT_THROW(vtp_bytes(s, wrong), InputError);
}

TEST(VtkIo, VtuHasConsistentCounts) {
  const TetMesh m = cube_mesh(1.0);
  std::vector<Eigen::Vector3d> u(m.node_count(), Eigen::Vector3d(0.1, 0, 0));
  const std::string xml = vtu_bytes(m, &u);
  std::smatch match;
  ASSERT_TRUE(std::regex_search(xml, match, std::regex("NumberOfPoints=\"(\\d+)\" NumberOfCells=\"(\\d+)\"")));
  EXPECT_EQ(std::stoul(match[1]), m.node_count());
  EXPECT_EQ(std::stoul(match[2]), m.tet_count());
  // Every opened tag is closed (minimal well-formedness for the tags used).
  for (const char* tag : {"VTKFile", "UnstructuredGrid", "Piece", "Points", "Cells", "CellData", "PointData", "DataArray"}) {
    const std::regex open(std::string("<") + tag + "[ >]"), close(std::string("</") + tag + ">");
    const auto n_open = std::distance(std::sregex_iterator(xml.begin(), xml.end(), open), std::sregex_iterator());
    const auto n_close = std::distance(std::sregex_iterator(xml.begin(), xml.end(), close), std::sregex_iterator());
    EXPECT_EQ(n_open, n_close) << tag;
    EXPECT_GT(n_open, 0) << tag;
  }
  // Six tets of type 10 and the labels in the same count.
  const std::size_t types_at = xml.find("Name=\"types\"");
  const std::string types = xml.substr(xml.find('>', types_at) + 1, xml.find("</DataArray>", types_at) - xml.find('>', types_at) - 1);
  EXPECT_EQ(std::count(types.begin(), types.end(), '\n') - 1, static_cast<long>(m.tet_count()));
  std::vector<Eigen::Vector3d> short_u(3);
  EXPECT_THROW(vtu_bytes(m, &short_u), InputError);
}

}  // namespace
}  // namespace brainshift
