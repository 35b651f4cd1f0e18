#include "field/displacement_field.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/smoothstep.h"
#include "core/timer.h"
#include "field/field_fill.h"
#include "field/tissue_guard.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "image/morphology.h"

namespace brainshift {
namespace {

constexpr float kUncovered = -std::numeric_limits<float>::infinity();

void validate(const TetMesh& mesh, const MeshDeformation& deformation, const Grid3& grid,
              const FieldParameters& params) {
  if (!(params.blend_distance_mm > 0.0) || !(params.barycentric_tolerance >= 0.0) ||
      params.smoothing_sweeps < 0) {
    throw InputError("pullback_field: parameters need blend_distance_mm > 0, "
                     "barycentric_tolerance >= 0 and smoothing_sweeps >= 0");
  }
  if (deformation.nonrigid_mm.size() != mesh.node_count()) {
    throw InputError("pullback_field: deformation has " +
                     std::to_string(deformation.nonrigid_mm.size()) +
                     " non-rigid vectors for a mesh of " + std::to_string(mesh.node_count()) +
                     " nodes");
  }
  const int n = static_cast<int>(mesh.node_count());
  for (const auto& tet : mesh.tets) {
    for (const int node : tet) {
      if (node < 0 || node >= n) {
        throw InputError("pullback_field: a tet references node " + std::to_string(node) +
                         " of a mesh with " + std::to_string(n) + " nodes");
      }
    }
  }
  if (grid.voxel_count() == 0) throw InputError("pullback_field: the intraop grid is empty");
  if (grid.voxel_count() > std::numeric_limits<std::uint32_t>::max()) {
    throw InputError("pullback_field: the intraop grid has more than 2^32 voxels");
  }
  const Eigen::Matrix3d a = deformation.intraop_from_preop.topLeftCorner<3, 3>();
  if (!deformation.intraop_from_preop.allFinite() || std::abs(a.determinant()) < 1e-9) {
    throw InputError("pullback_field: intraop_from_preop is singular or not finite");
  }
}

// Per-voxel result of the rasterisation: the pulled-back preop point is written
// into the field as u = p - x; depth = min barycentric coordinate of the owner.
struct Raster {
  VectorImage3* field;
  std::vector<float> depth;
};

// lambda_m(i,j,k) = c[m] + g[m] . (i,j,k), m = 0..3, in voxel index coordinates
// (barycentric coordinates are invariant under the affine voxel<->world map).
struct TetScan {
  std::array<double, 4> c;
  std::array<Eigen::Vector3d, 4> g;
  std::array<int, 3> lo, hi;  // voxel bounding box, clipped to the grid
};

bool make_scan(const std::array<Eigen::Vector3d, 4>& v, const Grid3& grid, double tol,
               TetScan& scan, double& det) {
  Eigen::Matrix3d t;
  t << v[1] - v[0], v[2] - v[0], v[3] - v[0];
  det = t.determinant();
  const double scale = (v[1] - v[0]).norm() * (v[2] - v[0]).norm() * (v[3] - v[0]).norm();
  if (!(std::abs(det) > 1e-12 * scale) || !std::isfinite(det)) return false;
  const Eigen::Matrix3d inv = t.inverse();
  scan.g[0] = -(inv.row(0) + inv.row(1) + inv.row(2)).transpose();
  scan.c[0] = 1.0;
  for (int m = 1; m < 4; ++m) {
    scan.g[m] = inv.row(m - 1).transpose();
    scan.c[m] = -scan.g[m].dot(v[0]);
    scan.c[0] -= scan.c[m];
  }
  for (int a = 0; a < 3; ++a) {
    const double mn = std::min({v[0][a], v[1][a], v[2][a], v[3][a]});
    const double mx = std::max({v[0][a], v[1][a], v[2][a], v[3][a]});
    scan.lo[a] = std::max(0, static_cast<int>(std::ceil(mn - 1e-6)));
    scan.hi[a] = std::min(grid.dims[a] - 1, static_cast<int>(std::floor(mx + 1e-6)));
  }
  return true;
}

// Range of i on row (j,k) where every lambda >= -tol (lambda is linear in i).
bool row_interval(const TetScan& s, int j, int k, double tol, int& i0, int& i1) {
  double lo = s.lo[0], hi = s.hi[0];
  for (int m = 0; m < 4; ++m) {
    const double base = s.c[m] + s.g[m].y() * j + s.g[m].z() * k + tol;
    const double slope = s.g[m].x();
    if (slope > 0) {
      lo = std::max(lo, -base / slope);
    } else if (slope < 0) {
      hi = std::min(hi, -base / slope);
    } else if (base < 0) {
      return false;
    }
  }
  // A nearly flat tet (a strongly compressed element) gives bounds far outside
  // the row: they must not reach the int conversion (overflow: a crash).
  if (!(lo <= hi)) return false;
  i0 = static_cast<int>(std::ceil(lo));
  i1 = static_cast<int>(std::floor(hi));
  return i0 <= i1;
}

void scan_tet(const TetScan& s, const std::array<Eigen::Vector3d, 4>& preop, const Grid3& grid,
              double tol, Raster& raster) {
  const Eigen::Matrix3d w_lin = grid.world_from_voxel.topLeftCorner<3, 3>();
  const Eigen::Vector3d w_off = grid.world_from_voxel.topRightCorner<3, 1>();
  for (int k = s.lo[2]; k <= s.hi[2]; ++k) {
    for (int j = s.lo[1]; j <= s.hi[1]; ++j) {
      int i0 = 0, i1 = -1;
      if (!row_interval(s, j, k, tol, i0, i1)) continue;
      std::size_t v = grid.index(i0, j, k);
      for (int i = i0; i <= i1; ++i, ++v) {
        const Eigen::Vector3d ijk(i, j, k);
        std::array<double, 4> lambda;
        for (int m = 0; m < 4; ++m) lambda[m] = s.c[m] + s.g[m].dot(ijk);
        const double depth = std::min({lambda[0], lambda[1], lambda[2], lambda[3]});
        if (depth <= raster.depth[v]) continue;
        raster.depth[v] = static_cast<float>(depth);
        // u = sum lambda_k p_k - x, with x = W ijk + t and sum lambda_k = 1.
        const Eigen::Vector3d p =
            lambda[0] * preop[0] + lambda[1] * preop[1] + lambda[2] * preop[2] + lambda[3] * preop[3];
        raster.field->vectors[v] = (p - w_lin * ijk - w_off).cast<float>();
      }
    }
  }
}

void rasterise(const TetMesh& mesh, const MeshDeformation& def, const Grid3& grid,
               double tol, Raster& raster, FieldStats& stats) {
  const Eigen::Matrix4d voxel_from_world = grid.voxel_from_world();
  std::vector<Eigen::Vector3d> node_voxel(mesh.node_count());
  for (std::size_t n = 0; n < mesh.node_count(); ++n) {
    const Eigen::Vector3d q = def.node_intraop_mm(mesh.nodes_mm[n], n);
    node_voxel[n] = (voxel_from_world * q.homogeneous()).head<3>();
  }
  // The grid's slices are split in two halves, one per thread; each scans
  // every tet but writes only its own slices, in the same tet order as one
  // thread would (so the owner of a voxel shared by two tets is the same).
  // Counts are taken by the half that starts at slice 0.
  const int nz = grid.dims[2];
  parallel_halves(static_cast<std::size_t>(nz), 4, [&](std::size_t k_begin, std::size_t k_end) {
    const bool counts = k_begin == 0;
    for (const auto& tet : mesh.tets) {
      const std::array<Eigen::Vector3d, 4> v{node_voxel[tet[0]], node_voxel[tet[1]],
                                             node_voxel[tet[2]], node_voxel[tet[3]]};
      TetScan scan;
      double det = 0;
      if (!make_scan(v, grid, tol, scan, det)) {
        if (counts) ++stats.skipped_tets;
        continue;
      }
      // Voxel axes may be left-handed, so orientation is judged against the grid's.
      if (counts && det * grid.world_from_voxel.topLeftCorner<3, 3>().determinant() < 0) ++stats.inverted_tets;
      scan.lo[2] = std::max(scan.lo[2], static_cast<int>(k_begin));
      scan.hi[2] = std::min(scan.hi[2], static_cast<int>(k_end) - 1);
      if (scan.lo[2] > scan.hi[2]) continue;
      const std::array<Eigen::Vector3d, 4> preop{mesh.nodes_mm[tet[0]], mesh.nodes_mm[tet[1]],
                                                 mesh.nodes_mm[tet[2]], mesh.nodes_mm[tet[3]]};
      scan_tet(scan, preop, grid, tol, raster);
    }
  });
}

// u = A^-1 x - x at voxel (i,j,k), evaluated as one affine map of the index.
struct AffinePullback {
  Eigen::Matrix3d lin;
  Eigen::Vector3d off;
  AffinePullback(const Eigen::Matrix4d& intraop_from_preop, const Grid3& grid) {
    const Eigen::Matrix4d inv = intraop_from_preop.inverse();
    const Eigen::Matrix3d m = inv.topLeftCorner<3, 3>() - Eigen::Matrix3d::Identity();
    lin = m * grid.world_from_voxel.topLeftCorner<3, 3>();
    off = m * grid.world_from_voxel.topRightCorner<3, 1>() + inv.topRightCorner<3, 1>();
  }
  Eigen::Vector3d operator()(int i, int j, int k) const { return lin * Eigen::Vector3d(i, j, k) + off; }
};

// Extends the non-rigid remainder beyond the covered voxels and composes the
// final field there (covered voxels keep their exact rasterised values), on a
// grid that holds every voxel the continuation reaches (continue_outside).
// With a guard (outline: its intraop outline on this box), the remainder is
// filled on every uncovered voxel outside the region, and the fade's weights
// are raised where it would pull preop tissue out of the brain
// (field/tissue_guard.h).
void continue_in_box(const MeshDeformation& deformation, const FieldParameters& params,
                     const Mask& covered, VectorImage3& field, FieldStats& stats, Mask* mesh_region,
                     const TissueGuard* guard, const Mask* outline) {
  const Grid3& grid = field.grid;
  const AffinePullback affine(deformation.intraop_from_preop, grid);
  std::vector<Eigen::Vector3f> rest(grid.voxel_count(), Eigen::Vector3f::Zero());
  for_each_voxel_on_both_cores(grid.dims, [&](std::size_t v, int i, int j, int k) {
    if (covered.voxels[v]) rest[v] = (field.vectors[v].cast<double>() - affine(i, j, k)).cast<float>();
  });
  // The brain region: the covered voxels and the cavities they enclose.
  const Mask region = fill_holes(covered);
  // Beyond the blend and the relaxed band the distance decides nothing.
  const ImageF distance = distance_to_mask_mm(region, std::max(params.blend_distance_mm, params.relax_band_mm));
  std::vector<std::uint32_t> free_voxels, relax_voxels;
  std::vector<float> weight(grid.voxel_count(), 0.f);
  parallel_halves(weight.size(), 1 << 16, [&](std::size_t begin, std::size_t end) {
    for (std::size_t v = begin; v < end; ++v)
      if (!covered.voxels[v]) weight[v] = static_cast<float>(1.0 - smoothstep(distance.voxels[v] / params.blend_distance_mm));
  });
  for (std::size_t v = 0; v < grid.voxel_count(); ++v) {
    if (covered.voxels[v]) continue;
    if (region.voxels[v]) ++stats.cavity_voxels;
    else if (weight[v] > 0.f) ++stats.blended_voxels;
    if (weight[v] > 0.f || (guard && !region.voxels[v])) free_voxels.push_back(static_cast<std::uint32_t>(v));
    if (region.voxels[v] || distance.voxels[v] <= params.relax_band_mm) {
      relax_voxels.push_back(static_cast<std::uint32_t>(v));
    }
  }
  fill_push_pull(grid, covered.voxels, free_voxels, rest);
  relax_laplace(grid, relax_voxels, params.smoothing_sweeps, rest);
  if (guard) {
    const TissueGuardStats g = guard_tissue(grid, covered.voxels, region.voxels, outline->voxels, rest,
                                            deformation.intraop_from_preop, *guard->preop_labels,
                                            guard->outline_tolerance_mm, params.blend_distance_mm, weight);
    stats.guard_landing_voxels += g.landing_voxels;
    stats.guard_raised_voxels += g.raised_voxels;
    stats.guard_unresolved_voxels += g.unresolved_voxels;
  }
  for_each_voxel_on_both_cores(grid.dims, [&](std::size_t v, int i, int j, int k) {
    if (!covered.voxels[v]) field.vectors[v] = (affine(i, j, k) + weight[v] * rest[v].cast<double>()).cast<float>();
  });
  if (mesh_region) *mesh_region = region;
}

// The continuation reaches max(blend_distance_mm, relax_band_mm) beyond the
// brain region, which lies in the covered voxels' bounding box (its cavities
// are enclosed by covered voxels); farther out the field is the affine alone.
// So it runs on that box grown by the reach and a voxel (a third to a half of
// a scan's grid), and the rest of the grid takes the affine. The same field
// as on the whole grid, but for the pyramid fill of the fading shell outside
// the brain, whose coarse cells are aligned to the box instead of the grid.
// The box's corner keeps the parity of i + j + k, so the Laplace sweeps'
// red-black colours are the grid's.
void continue_outside(const MeshDeformation& deformation, const FieldParameters& params,
                      const Mask& covered, VectorImage3& field, FieldStats& stats, Mask* mesh_region,
                      const TissueGuard* guard) {
  const Grid3& grid = field.grid;
  const AffinePullback affine(deformation.intraop_from_preop, grid);
  VoxelBox box = bounding_box_voxels(covered);
  if (box.empty) {
    for_each_voxel_on_both_cores(grid.dims, [&](std::size_t v, int i, int j, int k) { field.vectors[v] = affine(i, j, k).cast<float>(); });
    if (mesh_region) *mesh_region = Mask(grid, 0);
    return;
  }
  // A guarded continuation also holds every voxel where a pull-back can land
  // in preop tissue: the gap a sinking left lies beyond the sunken mesh.
  if (guard) {
    const VoxelBox tissue = preop_tissue_box(guard->preop_tissue_voxels, guard->preop_labels->grid,
                                             deformation.intraop_from_preop, grid);
    if (!tissue.empty)
      for (int a = 0; a < 3; ++a) box.lo[a] = std::min(box.lo[a], tissue.lo[a]), box.hi[a] = std::max(box.hi[a], tissue.hi[a]);
  }
  const double reach_mm = std::max(params.blend_distance_mm, params.relax_band_mm);
  box = grow_box(box, grid, reach_mm + grid.spacing_mm().maxCoeff());
  if ((box.lo[0] + box.lo[1] + box.lo[2]) % 2 != 0) {
    int a = 0;
    while (box.lo[a] == 0) ++a;  // an odd sum has a positive term
    --box.lo[a];
  }
  Grid3 sub;
  for (int a = 0; a < 3; ++a) sub.dims[a] = box.hi[a] - box.lo[a] + 1;
  sub.world_from_voxel = grid.world_from_voxel;
  sub.world_from_voxel.block<3, 1>(0, 3) = grid.world_mm(box.lo[0], box.lo[1], box.lo[2]);
  VectorImage3 part(sub);
  Mask part_covered(sub, 0), part_outline(sub, 0);
  const auto full_index = [&](int j, int k) { return grid.index(box.lo[0], j + box.lo[1], k + box.lo[2]); };
  for (int k = 0; k < sub.dims[2]; ++k)
    for (int j = 0; j < sub.dims[1]; ++j) {
      const std::size_t from = full_index(j, k), to = sub.index(0, j, k);
      std::copy_n(&field.vectors[from], sub.dims[0], &part.vectors[to]);
      std::copy_n(&covered.voxels[from], sub.dims[0], &part_covered.voxels[to]);
      if (guard) std::copy_n(&guard->intraop_outline->voxels[from], sub.dims[0], &part_outline.voxels[to]);
    }
  Mask part_region;
  continue_in_box(deformation, params, part_covered, part, stats, &part_region, guard, &part_outline);
  for_each_voxel_on_both_cores(grid.dims, [&](std::size_t v, int i, int j, int k) {
    const bool inside = i >= box.lo[0] && i <= box.hi[0] && j >= box.lo[1] && j <= box.hi[1] && k >= box.lo[2] &&
                        k <= box.hi[2];
    if (!inside) field.vectors[v] = affine(i, j, k).cast<float>();
  });
  for (int k = 0; k < sub.dims[2]; ++k)
    for (int j = 0; j < sub.dims[1]; ++j)
      std::copy_n(&part.vectors[sub.index(0, j, k)], sub.dims[0], &field.vectors[full_index(j, k)]);
  if (!mesh_region) return;
  *mesh_region = Mask(grid, 0);
  for (int k = 0; k < sub.dims[2]; ++k)
    for (int j = 0; j < sub.dims[1]; ++j)
      std::copy_n(&part_region.voxels[sub.index(0, j, k)], sub.dims[0], &mesh_region->voxels[full_index(j, k)]);
}

}  // namespace

VectorImage3 pullback_field(const TetMesh& preop_mesh, const MeshDeformation& deformation,
                            const Grid3& intraop_grid, const FieldParameters& params,
                            FieldStats* stats_out, Mask* mesh_region, const TissueGuard* guard) {
  validate(preop_mesh, deformation, intraop_grid, params);
  if (guard && (!guard->preop_labels || !guard->intraop_outline || !guard->intraop_outline->grid.same_geometry(intraop_grid)))
    throw InputError("pullback_field: the tissue guard needs the preop labels and an outline on the field's grid");
  Stopwatch total;
  FieldStats stats;
  VectorImage3 field(intraop_grid);
  Raster raster{&field, std::vector<float>(intraop_grid.voxel_count(), kUncovered)};
  rasterise(preop_mesh, deformation, intraop_grid, params.barycentric_tolerance, raster, stats);
  Mask covered(intraop_grid, 0);
  for (std::size_t v = 0; v < covered.voxels.size(); ++v) {
    covered.voxels[v] = raster.depth[v] != kUncovered;
    stats.covered_voxels += covered.voxels[v];
  }
  stats.rasterise_seconds = total.seconds();
  Stopwatch fill_timer;
  continue_outside(deformation, params, covered, field, stats, mesh_region, guard);
  stats.fill_seconds = fill_timer.seconds();
  stats.total_seconds = total.seconds();
  if (stats_out) *stats_out = stats;
  return field;
}

void to_json(nlohmann::json& j, const FieldStats& s) {
  j = {{"covered_voxels", s.covered_voxels},   {"cavity_voxels", s.cavity_voxels},
       {"blended_voxels", s.blended_voxels},   {"skipped_tets", s.skipped_tets},
       {"inverted_tets", s.inverted_tets},     {"rasterise_seconds", s.rasterise_seconds},
       {"guard_landing_voxels", s.guard_landing_voxels}, {"guard_raised_voxels", s.guard_raised_voxels},
       {"guard_unresolved_voxels", s.guard_unresolved_voxels},
       {"fill_seconds", s.fill_seconds},       {"total_seconds", s.total_seconds}};
}

}  // namespace brainshift
