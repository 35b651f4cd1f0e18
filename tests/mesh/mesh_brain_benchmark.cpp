// Measurement tool, not a test: meshes a brain mask (NIfTI voxels > 0, e.g.
// ch2bet.nii.gz) and prints mesh size, timings and quality.
//   mesh_brain_benchmark <mask.nii[.gz]> [cell facet distance (mm) [perturb exude bounds (deg)]]
// Why its own minimal NIfTI-1 reader (zlib): engine/image is written in
// parallel, and niftilib's nifti1_io.h needs nifti1.h, which Debian ships in
// libnifti2-dev (not installed here). Handles u8/i16/f32 and the sform or,
// failing that, the qform.
#include <zlib.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

#include "mesh/label_mesher.h"
#include "mesh/mesh_quality.h"
#include "mesh/surface_extraction.h"

namespace {

template <class T>
T field(const std::vector<char>& h, std::size_t offset) {
  T v;
  std::memcpy(&v, h.data() + offset, sizeof(T));
  return v;
}

Eigen::Matrix4d world_from_voxel(const std::vector<char>& h) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  if (field<std::int16_t>(h, 254) > 0) {  // sform_code: srow_x/y/z at 280
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) m(r, c) = field<float>(h, 280 + 16 * r + 4 * c);
    return m;
  }
  const double b = field<float>(h, 256), c = field<float>(h, 260), d = field<float>(h, 264);
  const double a = std::sqrt(std::max(0.0, 1 - b * b - c * c - d * d));
  const double qfac = field<float>(h, 76) < 0 ? -1 : 1;  // pixdim[0]
  Eigen::Matrix3d r;
  r << a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c),
      2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b),
      2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - c * c - b * b;
  const Eigen::Vector3d pixdim(field<float>(h, 80), field<float>(h, 84), qfac * field<float>(h, 88));
  m.topLeftCorner<3, 3>() = r * pixdim.asDiagonal();
  m.topRightCorner<3, 1>() = Eigen::Vector3d(field<float>(h, 268), field<float>(h, 272), field<float>(h, 276));
  return m;
}

brainshift::LabelImage read_mask(const char* path) {
  gzFile f = gzopen(path, "rb");
  if (!f) throw std::runtime_error(std::string("cannot open ") + path);
  std::vector<char> h(348);
  if (gzread(f, h.data(), 348) != 348 || field<std::int32_t>(h, 0) != 348)
    throw std::runtime_error(std::string(path) + ": not a little-endian NIfTI-1 file");
  brainshift::Grid3 g;
  g.dims = {field<std::int16_t>(h, 42), field<std::int16_t>(h, 44), field<std::int16_t>(h, 46)};
  g.world_from_voxel = world_from_voxel(h);
  const int datatype = field<std::int16_t>(h, 70), bitpix = field<std::int16_t>(h, 72);
  const float slope = field<float>(h, 112), inter = field<float>(h, 116);
  gzseek(f, static_cast<long>(field<float>(h, 108)), SEEK_SET);  // vox_offset
  std::vector<char> data(g.voxel_count() * (bitpix / 8));
  if (gzread(f, data.data(), static_cast<unsigned>(data.size())) != static_cast<int>(data.size()))
    throw std::runtime_error(std::string(path) + ": truncated data");
  gzclose(f);
  brainshift::LabelImage mask(g, 0);
  for (std::size_t v = 0; v < g.voxel_count(); ++v) {
    double value = 0;
    if (datatype == 2) value = static_cast<unsigned char>(data[v]);
    else if (datatype == 4) value = field<std::int16_t>(data, 2 * v);
    else if (datatype == 16) value = field<float>(data, 4 * v);
    else throw std::runtime_error("unsupported NIfTI datatype " + std::to_string(datatype));
    if (slope != 0) value = value * slope + inter;
    mask.voxels[v] = value > 0 ? 1 : 0;
  }
  return mask;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2 && argc != 5 && argc != 7) {
    std::fprintf(stderr, "usage: %s mask.nii[.gz] [cell_size_mm facet_size_mm facet_distance_mm [perturb_bound_deg exude_bound_deg]]\n", argv[0]);
    return 2;
  }
  const brainshift::LabelImage mask = read_mask(argv[1]);
  brainshift::MeshingParameters p;
  if (argc == 7) {  // perturb bound <= 0: no perturbation; exude bound < 0: no optimisation
    p.perturb_sliver_bound_deg = std::atof(argv[5]), p.exude_sliver_bound_deg = std::atof(argv[6]);
    p.perturb = p.perturb_sliver_bound_deg > 0;
    p.optimise = p.exude_sliver_bound_deg >= 0;
  }
  if (argc >= 5) p.cell_size_mm = std::atof(argv[2]), p.facet_size_mm = std::atof(argv[3]), p.facet_distance_mm = std::atof(argv[4]);
  std::size_t voxels = 0;
  for (auto v : mask.voxels) voxels += v;
  brainshift::MeshingStats stats;
  const brainshift::TetMesh mesh = brainshift::mesh_label_image(mask, p, &stats);
  const brainshift::MeshQuality q = brainshift::measure_quality(mesh);
  // A cheap fingerprint to compare runs across processes (determinism).
  std::size_t hash = mesh.node_count();
  for (const auto& x : mesh.nodes_mm) hash = hash * 1000003u ^ std::hash<double>{}(x.x() + 3 * x.y() + 7 * x.z());
  for (const auto& t : mesh.tets) hash = hash * 1000003u ^ std::size_t(t[0] + 7 * t[1] + 13 * t[2] + 17 * t[3]);
  std::printf("cell %.2f facet %.2f distance %.2f mm, perturb %s (%.1f deg), exude %s (%.1f deg)\n", p.cell_size_mm,
              p.facet_size_mm, p.facet_distance_mm, p.optimise && p.perturb ? "on" : "off", p.perturb_sliver_bound_deg,
              p.optimise ? "on" : "off", p.exude_sliver_bound_deg);
  std::printf("mask %.1f ml, mesh %.1f ml\n", voxels * std::abs(mask.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000, q.total_volume_mm3 / 1000);
  std::printf("nodes %zu tets %zu boundary_faces %zu boundary_nodes %zu\n", q.nodes, q.tets, q.boundary_faces, brainshift::boundary_nodes(mesh).size());
  std::printf("min dihedral %.2f max dihedral %.2f max radius-edge %.2f inverted %zu degenerate %zu dropped %zu\n",
              q.min_dihedral_deg, q.max_dihedral_deg, q.max_radius_edge_ratio, q.inverted_tets, q.degenerate_tets, stats.dropped_degenerate);
  std::printf("time refine %.2f s optimise %.2f s total %.2f s, components %zu, island tets dropped %zu, outer surface components %zu\n",
              stats.seconds_refine, stats.seconds_optimise, stats.seconds_total, stats.seed_components, stats.dropped_island_tets,
              brainshift::count_connected_components(brainshift::extract_boundary_surface(mesh, 0)));
  std::printf("fingerprint %zx\n", hash);
  return 0;
}
