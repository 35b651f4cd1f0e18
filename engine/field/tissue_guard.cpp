#include "field/tissue_guard.h"

#include <algorithm>
#include <cmath>
#include <optional>

#include "core/parallel.h"
#include "image/distance_map.h"

namespace brainshift {
namespace {

// Preop tissue at a point given in preop voxel coordinates: the nearest
// voxel's label is not 0.
bool tissue_at(const LabelImage& labels, const Eigen::Vector3d& voxel) {
  std::array<int, 3> ijk;
  for (int a = 0; a < 3; ++a) {
    ijk[a] = static_cast<int>(std::lround(voxel[a]));
    if (ijk[a] < 0 || ijk[a] >= labels.grid.dims[a]) return false;
  }
  return labels.at(ijk[0], ijk[1], ijk[2]) != 0;
}

// w(x) = max(w(x), max_y (w(y) - |x - y| / length_mm)) over the box, by two
// chamfer passes of the 26-neighbourhood (each voxel takes its 13 earlier
// neighbours going forward, the 13 later going back): a Lipschitz spread of
// the raised weights, exact along the grid's axes and diagonals.
void spread_weights(const Grid3& g, const VoxelBox& box, double length_mm, std::vector<float>& w) {
  const Eigen::Matrix3d lin = g.world_from_voxel.topLeftCorner<3, 3>();
  struct Step {
    int di, dj, dk;
    std::ptrdiff_t offset;
    float drop;
  };
  const auto nx = static_cast<std::ptrdiff_t>(g.dims[0]), nxy = nx * g.dims[1];
  std::vector<Step> earlier;
  for (int dk = -1; dk <= 1; ++dk)
    for (int dj = -1; dj <= 1; ++dj)
      for (int di = -1; di <= 1; ++di) {
        const bool before = dk < 0 || (dk == 0 && (dj < 0 || (dj == 0 && di < 0)));
        if (!before) continue;
        const double mm = (lin * Eigen::Vector3d(di, dj, dk)).norm();
        earlier.push_back({di, dj, dk, di + dj * nx + dk * nxy, static_cast<float>(mm / length_mm)});
      }
  const auto pass = [&](int sign) {
    const int k0 = sign > 0 ? box.lo[2] : box.hi[2], k1 = sign > 0 ? box.hi[2] : box.lo[2];
    const int j0 = sign > 0 ? box.lo[1] : box.hi[1], j1 = sign > 0 ? box.hi[1] : box.lo[1];
    const int i0 = sign > 0 ? box.lo[0] : box.hi[0], i1 = sign > 0 ? box.hi[0] : box.lo[0];
    for (int k = k0; k != k1 + sign; k += sign)
      for (int j = j0; j != j1 + sign; j += sign)
        for (int i = i0; i != i1 + sign; i += sign) {
          const std::size_t v = g.index(i, j, k);
          // Only the box's faces need the bounds test.
          const bool inner = i > box.lo[0] && i < box.hi[0] && j > box.lo[1] && j < box.hi[1] &&
                             k > box.lo[2] && k < box.hi[2];
          float here = w[v];
          for (const Step& s : earlier) {
            if (!inner) {
              const int a = i + sign * s.di, b = j + sign * s.dj, c = k + sign * s.dk;
              if (a < box.lo[0] || a > box.hi[0] || b < box.lo[1] || b > box.hi[1] || c < box.lo[2] || c > box.hi[2])
                continue;
            }
            here = std::max(here, w[static_cast<std::size_t>(static_cast<std::ptrdiff_t>(v) + sign * s.offset)] - s.drop);
          }
          w[v] = here;
        }
  };
  pass(1);
  pass(-1);
}

}  // namespace

TissueGuardStats guard_tissue(const Grid3& g, const std::vector<std::uint8_t>& covered,
                              const std::vector<std::uint8_t>& region, const std::vector<std::uint8_t>& outline,
                              const std::vector<Eigen::Vector3f>& rest, const Eigen::Matrix4d& intraop_from_preop,
                              const LabelImage& preop_labels, double outline_tolerance_mm, double blend_distance_mm,
                              std::vector<float>& weight) {
  // A voxel's pull-back in preop voxel coordinates: affine landing + w L r.
  const Eigen::Matrix4d preop_voxel_from_world = preop_labels.grid.voxel_from_world();
  const Eigen::Matrix4d landing = preop_voxel_from_world * intraop_from_preop.inverse() * g.world_from_voxel;
  const Eigen::Matrix3d L = preop_voxel_from_world.topLeftCorner<3, 3>();
  const std::size_t n = g.voxel_count();
  // The weight each landing voxel needs (0 elsewhere), found side by side.
  std::vector<float> need(n, 0.f);
  std::vector<std::uint8_t> unresolved(n, 0);
  Mask brain(g, 0);
  for (std::size_t v = 0; v < n; ++v) brain.voxels[v] = region[v] || outline[v];
  const std::optional<ImageF> near =
      outline_tolerance_mm > 0 ? std::optional<ImageF>(distance_to_mask_mm(brain, outline_tolerance_mm)) : std::nullopt;
  for_each_voxel_on_both_cores(g.dims, [&](std::size_t v, int i, int j, int k) {
    if (brain.voxels[v] || (near && near->voxels[v] <= outline_tolerance_mm)) return;
    const Eigen::Vector3d base = (landing * Eigen::Vector4d(i, j, k, 1)).head<3>();
    const Eigen::Vector3d r = L * rest[v].cast<double>();
    if (!tissue_at(preop_labels, base + weight[v] * r)) return;
    if (tissue_at(preop_labels, base + r)) {
      need[v] = 1.f;
      unresolved[v] = 1;
      return;
    }
    // The landing leaves the tissue somewhere in (w, 1]: 12 halvings place it
    // within 1/4096 of the remainder (< 0.01 mm for a 30 mm remainder).
    double lo = weight[v], hi = 1.0;
    for (int step = 0; step < 12; ++step) {
      const double mid = 0.5 * (lo + hi);
      (tissue_at(preop_labels, base + mid * r) ? lo : hi) = mid;
    }
    need[v] = static_cast<float>(hi);
  });
  TissueGuardStats stats;
  VoxelBox landing_box;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        if (need[v] <= 0.f) continue;
        ++stats.landing_voxels;
        stats.unresolved_voxels += unresolved[v];
        const std::array<int, 3> ijk{i, j, k};
        for (int a = 0; a < 3; ++a) {
          landing_box.lo[a] = landing_box.empty ? ijk[a] : std::min(landing_box.lo[a], ijk[a]);
          landing_box.hi[a] = landing_box.empty ? ijk[a] : std::max(landing_box.hi[a], ijk[a]);
        }
        landing_box.empty = false;
      }
  if (landing_box.empty) return stats;
  const VoxelBox reach = grow_box(landing_box, g, blend_distance_mm);
  spread_weights(g, reach, blend_distance_mm, need);
  for (int k = reach.lo[2]; k <= reach.hi[2]; ++k)
    for (int j = reach.lo[1]; j <= reach.hi[1]; ++j)
      for (int i = reach.lo[0]; i <= reach.hi[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        if (covered[v] || region[v] || need[v] <= weight[v]) continue;
        weight[v] = need[v];
        ++stats.raised_voxels;
      }
  return stats;
}

VoxelBox tissue_voxel_box(const LabelImage& labels) { return bounding_box_voxels(nonzero_mask(labels)); }

VoxelBox preop_tissue_box(const VoxelBox& tissue, const Grid3& preop_grid, const Eigen::Matrix4d& intraop_from_preop,
                          const Grid3& grid) {
  if (tissue.empty) return VoxelBox{};
  const Eigen::Matrix4d to_voxel = grid.voxel_from_world() * intraop_from_preop * preop_grid.world_from_voxel;
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
  for (int c = 0; c < 8; ++c) {
    // The corners of the box's outer voxel faces.
    const Eigen::Vector3d corner((c & 1 ? tissue.hi[0] + 0.5 : tissue.lo[0] - 0.5),
                                 (c & 2 ? tissue.hi[1] + 0.5 : tissue.lo[1] - 0.5),
                                 (c & 4 ? tissue.hi[2] + 0.5 : tissue.lo[2] - 0.5));
    const Eigen::Vector3d v = (to_voxel * corner.homogeneous()).head<3>();
    lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
  }
  VoxelBox out;
  for (int a = 0; a < 3; ++a) {
    out.lo[a] = std::max(0, static_cast<int>(std::floor(lo[a])));
    out.hi[a] = std::min(grid.dims[a] - 1, static_cast<int>(std::ceil(hi[a])));
    if (out.lo[a] > out.hi[a]) return VoxelBox{};
  }
  out.empty = false;
  return out;
}

}  // namespace brainshift
