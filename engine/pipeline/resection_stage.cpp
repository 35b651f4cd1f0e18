#include "pipeline/resection_stage.h"

#include <cmath>
#include <limits>

#include "core/errors.h"
#include "core/timer.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "mesh/surface_self_intersection.h"
#include "registration/active_surface.h"

namespace brainshift {
namespace {

// Generalised winding number of a closed surface with outward triangles at p
// (1 inside, 0 outside): the solid angles of its triangles (Van Oosterom and
// Strackee) over 4 pi.
double winding_number(const TriSurface& s, const Eigen::Vector3d& p) {
  double sum = 0;
  for (const auto& t : s.triangles) {
    const Eigen::Vector3d a = s.vertices_mm[t[0]] - p, b = s.vertices_mm[t[1]] - p, c = s.vertices_mm[t[2]] - p;
    const double la = a.norm(), lb = b.norm(), lc = c.norm();
    sum += 2 * std::atan2(a.dot(b.cross(c)), la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la);
  }
  return sum / (4 * 3.14159265358979323846);
}

// Resection cavity candidates within the box: non-tissue voxels enclosed by
// the intraop brain (an internal cavity is filled in the outline,
// brain_region, but carries no label; sulcal CSF open to the outside is not
// in the outline), and non-tissue voxels inside the structure's wall where
// the first solve put it, enclosed or not: a cavity open to the surface
// through the surgical corridor is still where the structure was. Only the
// box is scanned: this runs on every scan.
Mask cavity_candidates(const LabelImage& labels, const Mask& brain_region, const VoxelBox& box,
                       const TriSurface& wall_now) {
  Mask m = crop_to_box(brain_region, box);
  const Grid3& g = labels.grid;
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;  // the wall's own extent
  for (const auto& p : wall_now.vertices_mm) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  std::size_t v = 0;
  for (int k = box.lo[2]; k <= box.hi[2]; ++k)
    for (int j = box.lo[1]; j <= box.hi[1]; ++j)
      for (int i = box.lo[0]; i <= box.hi[0]; ++i, ++v) {
        if (labels.at(i, j, k) != 0) {
          m.voxels[v] = 0;
          continue;
        }
        if (m.voxels[v]) continue;
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        if ((x.array() >= lo.array()).all() && (x.array() <= hi.array()).all() && winding_number(wall_now, x) > 0.5)
          m.voxels[v] = 1;
      }
  return m;
}

// Voxel box of the grid holding every point, grown by margin_mm.
VoxelBox box_around(const std::vector<Eigen::Vector3d>& points_mm, const Grid3& grid, double margin_mm) {
  VoxelBox box;
  const Eigen::Matrix4d voxel_from_world = grid.voxel_from_world();
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::max()), hi = -lo;
  for (const auto& p : points_mm) {
    const Eigen::Vector3d v = (voxel_from_world * p.homogeneous()).head<3>();
    lo = lo.cwiseMin(v);
    hi = hi.cwiseMax(v);
  }
  for (int a = 0; a < 3; ++a) {
    box.lo[a] = std::max(0, static_cast<int>(std::floor(lo[a])));
    box.hi[a] = std::min(grid.dims[a] - 1, static_cast<int>(std::ceil(hi[a])));
    if (box.hi[a] < box.lo[a]) return VoxelBox{};
  }
  box.empty = points_mm.empty();
  return box.empty ? box : grow_box(box, grid, margin_mm);
}

// The wall where the affine and the system-0 solve put it.
TriSurface wall_after_first_solve(const ResectableWall& r, const Eigen::Matrix4d& A,
                                  const std::vector<Eigen::Vector3d>& nonrigid_mm) {
  TriSurface s = r.wall;
  for (std::size_t v = 0; v < s.vertices_mm.size(); ++v)
    s.vertices_mm[v] = (A * s.vertices_mm[v].homogeneous()).head<3>() + nonrigid_mm[s.mesh_node[v]];
  return s;
}

struct Candidate {
  const ResectableWall* wall = nullptr;
  TriSurface start;
  Mask cavity;  // cropped around the wall
  double cavity_ml = 0;
};

// Boundary values of the wall's system: system-0 values where a node is fixed
// there already (the brain surface and ventricle walls win), the matched wall
// elsewhere; wall vertices the match left far from the cavity (an unresected
// part of the structure) keep their system-0 displacement.
std::vector<Eigen::Vector3d> values_for(const WarmState& warm, const ResectableWall& r,
                                        const SurfaceMatchResult& m, const std::vector<Eigen::Vector3d>& nonrigid_mm,
                                        const std::vector<Eigen::Vector3d>& fixed_values_mm, double max_residual_mm,
                                        std::size_t* unmatched) {
  const auto& fixed = warm.fem.fixed_nodes(r.system);
  std::vector<Eigen::Vector3d> values(fixed.size(), Eigen::Vector3d::Zero());
  *unmatched = 0;
  for (std::size_t v = 0; v < r.wall.mesh_node.size(); ++v) {
    const int node = r.wall.mesh_node[v];
    const double residual = m.residual_distance_mm[v];
    const bool reached = std::isfinite(residual) && residual <= max_residual_mm;
    if (!reached) ++*unmatched;
    values[r.fixed_index_of_node[node]] = nonrigid_mm[node] + (reached ? m.displacement_mm[v] : Eigen::Vector3d::Zero());
  }
  for (std::size_t i = 0; i < fixed.size(); ++i) {
    const int first = warm.fixed_index_of_node[fixed[i]];
    if (first >= 0) values[i] = fixed_values_mm[first];
  }
  return values;
}

}  // namespace

ResectionMatch match_resection(const WarmState& warm, const IntraopInput& input, const Mask& brain_region,
                               const Eigen::Matrix4d& A, const std::vector<Eigen::Vector3d>& nonrigid_mm,
                               const std::vector<Eigen::Vector3d>& fixed_values_mm,
                               const PipelineParameters& params) {
  ResectionMatch out;
  if (warm.resectables.empty()) return out;
  Stopwatch watch;
  // The structure whose neighbourhood holds the largest cavity.
  Candidate best;
  for (const auto& r : warm.resectables) {
    Candidate c{&r, wall_after_first_solve(r, A, nonrigid_mm), {}, 0};
    const VoxelBox box = box_around(c.start.vertices_mm, brain_region.grid, 10.0);
    nlohmann::json& m = out.metrics["structures"][r.name];
    m = {{"preop_volume_ml", r.volume_ml}, {"cavity_ml", 0.0}, {"resected", false}};
    if (box.empty) continue;
    c.cavity = cavity_candidates(input.labels, brain_region, box, c.start);
    c.cavity_ml = volume_ml(c.cavity);
    m["cavity_ml"] = c.cavity_ml;
    if (c.cavity_ml >= params.min_resection_cavity_ml && c.cavity_ml > best.cavity_ml) best = std::move(c);
  }
  if (!best.wall) return out;
  const ResectableWall& r = *best.wall;
  nlohmann::json& m = out.metrics["structures"][r.name];
  const ImageF target = signed_distance_mm(best.cavity);
  const SurfaceMatchResult match =
      match_surface(best.start, target, params.resection_surface, input.t1 ? &*input.t1 : nullptr);
  TriSurface matched = best.start;
  for (std::size_t v = 0; v < matched.vertices_mm.size(); ++v) matched.vertices_mm[v] += match.displacement_mm[v];
  std::size_t crossings = 0;
  try {
    crossings = count_self_intersections(matched);
  } catch (const InputError&) {
    // Not a polygon mesh: the flipped-triangle check below still applies.
  }
  std::size_t unmatched = 0;
  m.update({{"wall_vertices", r.wall.vertices_mm.size()}, {"iterations", match.iterations},
            {"mean_residual_mm", match.mean_residual_mm}, {"max_residual_mm", match.max_residual_mm},
            {"flipped_triangles", match.flipped_triangles}, {"self_intersections", crossings}});
  if (match.flipped_triangles > 0 || crossings > 0 ||
      match.mean_residual_mm > params.gates.max_mean_surface_residual_mm) {
    m["resected"] = "cavity found but the wall match was refused (folded, self-intersecting or diverged)";
  } else {
    out.fixed_values_mm = values_for(warm, r, match, nonrigid_mm, fixed_values_mm,
                                     params.gates.max_mean_surface_residual_mm, &unmatched);
    out.system = r.system;
    m["resected"] = true;
    m["wall_vertices_without_cavity"] = unmatched;
  }
  out.metrics["seconds"] = watch.seconds();
  return out;
}

}  // namespace brainshift
