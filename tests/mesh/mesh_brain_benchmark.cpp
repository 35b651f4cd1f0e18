// Measurement tool, not a test: meshes a brain mask (NIfTI voxels > 0, e.g.
// ch2bet.nii.gz) and prints mesh size, timings and quality.
//   mesh_brain_benchmark <mask.nii[.gz]> [cell facet distance (mm) [perturb exude bounds (deg)]]
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

#include "image/nifti_io.h"
#include "mesh/label_mesher.h"
#include "mesh/mesh_quality.h"
#include "mesh/surface_extraction.h"

namespace {

// Voxels > 0 of any NIfTI scalar image (the project's reader: NIfTI-1/-2, gzip).
brainshift::LabelImage read_mask(const char* path) {
  const brainshift::ImageF image = brainshift::read_scalar_image(path);
  brainshift::LabelImage mask(image.grid, 0);
  for (std::size_t v = 0; v < image.voxels.size(); ++v) mask.voxels[v] = image.voxels[v] > 0 ? 1 : 0;
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
