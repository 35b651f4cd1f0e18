#include "pipeline/surface_stage.h"

#include <algorithm>
#include <future>
#include <optional>

#include "core/errors.h"
#include "mesh/surface_self_intersection.h"
#include "registration/active_surface.h"
#include "registration/linear_sampler.h"
#include "registration/surface_repair.h"

namespace brainshift {
namespace {

TriSurface mapped_by_affine(const TriSurface& surface, const Eigen::Matrix4d& intraop_from_preop) {
  TriSurface out = surface;
  for (auto& v : out.vertices_mm) v = (intraop_from_preop * v.homogeneous()).head<3>();
  return out;
}

// The preop contact pairs in the intraop frame: directions through the
// affine's linear part, gaps scaled with them.
ContactPairs mapped_by_affine(const ContactPairs& contacts, const Eigen::Matrix4d& intraop_from_preop) {
  ContactPairs out = contacts;
  const Eigen::Matrix3d L = intraop_from_preop.topLeftCorner<3, 3>();
  for (auto& c : out) {
    const Eigen::Vector3d d = L * c.direction_from_vertex;
    c.gap_mm *= d.norm();
    c.direction_from_vertex = d.normalized();
  }
  return out;
}

TriSurface moved(const TriSurface& start, const std::vector<Eigen::Vector3d>& u) {
  TriSurface out = start;
  for (std::size_t v = 0; v < out.vertices_mm.size(); ++v) out.vertices_mm[v] += u[v];
  return out;
}

struct Defects {
  std::size_t flipped = 0, crossing_pairs = 0;
  // Crossings of a small component moved whole (see mark_small_components):
  // reported, not repaired; the tissue between it and the surface it touches
  // is what the field's fold gate judges.
  std::size_t small_component_crossings = 0;
  std::optional<std::string> unchecked;  // crossings could not be computed (not a polygon mesh)
  std::vector<char> vertices;            // marked vertices
  bool any() const { return flipped > 0 || crossing_pairs > 0; }
};

// Flips and crossings of the surface at start + u. in_small: vertices of the
// small components (empty: none).
Defects geometric_defects(const TriSurface& start, const std::vector<Eigen::Vector3d>& u,
                          const std::vector<char>& in_small) {
  const TriSurface now = moved(start, u);
  Defects d;
  d.vertices.assign(start.vertices_mm.size(), 0);
  const auto mark = [&](int t) {
    for (int v : start.triangles[static_cast<std::size_t>(t)]) d.vertices[v] = 1;
  };
  const std::vector<int> flips = flipped_triangles(start, now.vertices_mm);
  d.flipped = flips.size();
  for (int t : flips) mark(t);
  try {
    const auto small = [&](int t) {
      return !in_small.empty() && in_small[start.triangles[static_cast<std::size_t>(t)][0]];
    };
    for (const auto& [a, b] : self_intersecting_triangle_pairs(now)) {
      if (small(a) || small(b)) {
        ++d.small_component_crossings;
        continue;
      }
      ++d.crossing_pairs;
      mark(a), mark(b);
    }
  } catch (const InputError& e) {
    d.unchecked = e.what();
  }
  return d;
}

// Marks the vertices of surface components smaller than min_area_mm2 (specks
// of a label, fragments of a thin horn that the mesher cut apart): too small
// to be segmented reliably intraop, they follow the reliable surface around
// them, each moving as a whole (a translation cannot fold or cross it).
// Returns those components.
std::vector<std::vector<int>> mark_small_components(const std::vector<std::vector<int>>& nb,
                                                    const std::vector<double>& area, double min_area_mm2,
                                                    std::vector<char>& marked) {
  std::vector<char> seen(nb.size(), 0);
  std::vector<int> stack, component;
  std::vector<std::vector<int>> small;
  for (std::size_t start = 0; start < nb.size(); ++start) {
    if (seen[start]) continue;
    component.clear();
    stack.assign(1, static_cast<int>(start));
    seen[start] = 1;
    double total = 0;
    while (!stack.empty()) {
      const int v = stack.back();
      stack.pop_back();
      component.push_back(v);
      total += area[v];
      for (int w : nb[v])
        if (!seen[w]) seen[w] = 1, stack.push_back(w);
    }
    if (total >= min_area_mm2) continue;
    for (int v : component) marked[v] = 1;
    small.push_back(component);
  }
  return small;
}

void translate_whole(const std::vector<std::vector<int>>& components, std::vector<Eigen::Vector3d>& u) {
  for (const auto& c : components) {
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    for (int v : c) mean += u[v];
    mean /= static_cast<double>(c.size());
    for (int v : c) u[v] = mean;
  }
}

double marked_area_fraction(const std::vector<char>& marked, const std::vector<double>& area) {
  double all = 0, bad = 0;
  for (std::size_t v = 0; v < area.size(); ++v) {
    all += area[v];
    if (marked[v]) bad += area[v];
  }
  return all > 0 ? bad / all : 0.0;
}

// The farthest any vertex must travel to reach the target, by the data: the
// largest |signed distance| at the start positions (vertices with data).
// The distance map gives the NEAREST target point; the matching point lies
// along the motion, 1 / cos(theta) farther when the target surface is slanted
// by theta against the motion (the walls of a sink or a retractor's dent).
// Cortical walls up to 60 degrees off the motion: a factor of 2. A diverged
// match runs off by centimetres beyond that (DESIGN.md "Quality gates").
constexpr double kMotionPerNearestDistance = 2.0;

double largest_data_distance_mm(const TriSurface& start, const ImageF& target) {
  const LinearSampler sampler(target);
  double m = 0;
  for (const auto& x : start.vertices_mm) {
    double d;
    if (sampler.sample(x, &d, nullptr)) m = std::max(m, std::abs(d));
  }
  return m;
}

}  // namespace

RepairedMatch match_and_repair(const TriSurface& start, const ContactPairs& contacts, const ImageF& target,
                               const ActiveSurfaceParameters& p, const SurfaceRepairParameters& rp, const ImageF* image,
                               double max_unsupported_mm) {
  RepairedMatch out{match_surface(start, target, p, image, &contacts), {}, ""};
  std::vector<Eigen::Vector3d>& u = out.match.displacement_mm;
  if (!std::all_of(u.begin(), u.end(), [](const Eigen::Vector3d& x) { return x.allFinite(); })) {
    out.unsafe = "diverged (non-finite displacements)";
    out.repair = {{"non_finite", true}};
    return out;
  }
  const std::vector<double> area = vertex_areas_mm2(start);
  const auto neighbours = rp.enabled ? surface_vertex_neighbours(start) : std::vector<std::vector<int>>{};
  std::vector<char> in_small(rp.enabled ? u.size() : 0, 0);
  const auto small = rp.enabled ? mark_small_components(neighbours, area, rp.min_component_area_mm2, in_small)
                                : std::vector<std::vector<int>>{};
  std::size_t small_vertices = 0;
  for (const auto& c : small) small_vertices += c.size();
  Defects d = geometric_defects(start, u, in_small);
  // Vertices left far from their target: the match could not follow the data
  // there (an island, a structure the segmenter missed); their neighbours can.
  std::vector<char> unreliable = d.vertices;
  for (std::size_t v = 0; v < in_small.size(); ++v) unreliable[v] |= in_small[v];
  std::size_t far = 0;
  for (std::size_t v = 0; v < u.size(); ++v) {
    const double r = out.match.residual_distance_mm[v];
    if (r > rp.unreliable_residual_mm) unreliable[v] = 1, ++far;
  }
  nlohmann::json& report = out.repair;
  report = {{"flipped_triangles_before", d.flipped}, {"crossing_pairs_before", d.crossing_pairs},
            {"far_vertices_before", far}, {"small_components", small.size()}, {"small_component_vertices", small_vertices}};
  if (d.unchecked) report["crossings"] = "not checked: " + *d.unchecked;
  const auto count_marked = [&] { return static_cast<std::size_t>(std::count(unreliable.begin(), unreliable.end(), 1)); };
  int rounds = 0;
  std::size_t unreached = 0;
  double max_change_mm = 0;
  std::size_t rescued = 0;
  if (rp.enabled && count_marked() > 0) {
    const std::vector<Eigen::Vector3d> matched = u;
    for (rounds = 1; rounds <= rp.rounds; ++rounds) {
      grow_marked(unreliable, neighbours, 1);
      u = matched;
      // A defect left after a round takes a wider mean in the next: a
      // smoother field is less likely to fold.
      const double sigma = std::min(rp.smoothing_mm * (1 + 0.5 * (rounds - 1)), rp.max_search_mm / 3);
      unreached = fill_from_reliable_neighbours(start.vertices_mm, unreliable, u, sigma, rp.max_search_mm);
      translate_whole(small, u);
      d = geometric_defects(start, u, in_small);
      if (!d.any()) break;
      for (std::size_t v = 0; v < u.size(); ++v) unreliable[v] |= d.vertices[v];
    }
    rounds = std::min(rounds, rp.rounds);
    // Folds the fill made (a filled patch beside a steep, matched one): the
    // fold guard takes those vertices back toward the match, which the guard
    // kept unfolded, only as far as needed. Folding is solved, not refused.
    if (d.flipped > 0 && p.fold_guard_enabled) {
      rescued = limit_folding(start, matched, u, p.fold_guard);
      d = geometric_defects(start, u, in_small);
    }
    for (std::size_t v = 0; v < u.size(); ++v) max_change_mm = std::max(max_change_mm, (u[v] - matched[v]).norm());
  }
  const double fraction = marked_area_fraction(unreliable, area);
  report["repaired_vertices"] = rp.enabled ? count_marked() : 0;
  report["repaired_area_fraction"] = rp.enabled ? fraction : 0.0;
  report["rounds"] = rounds;
  report["fold_guard_vertices"] = rescued;
  report["vertices_left_affine"] = unreached;
  report["max_change_mm"] = max_change_mm;
  double max_u = 0;
  for (const auto& x : u) max_u = std::max(max_u, x.norm());
  const double data_mm = largest_data_distance_mm(start, target);
  report["max_displacement_mm"] = max_u;
  report["max_data_distance_mm"] = data_mm;
  report["flipped_triangles_after"] = d.flipped;
  report["crossing_pairs_after"] = d.crossing_pairs;
  report["small_component_crossings_after"] = d.small_component_crossings;
  out.match.flipped_triangles = d.flipped;
  if (d.flipped > 0)
    out.unsafe = "folded " + std::to_string(d.flipped) + " triangles" + (rp.enabled ? " after repair" : "");
  else if (d.crossing_pairs > 0)
    out.unsafe = "self-intersects (" + std::to_string(d.crossing_pairs) + " pairs of crossing triangles" +
                 (rp.enabled ? " after repair)" : ")");
  else if (max_u > kMotionPerNearestDistance * data_mm + max_unsupported_mm)
    out.unsafe = "moves " + std::to_string(max_u) + " mm where the data show at most " + std::to_string(data_mm) +
                 " mm to the nearest target (allowed: 2 x that + " + std::to_string(max_unsupported_mm) + " mm)";
  return out;
}

std::string field_beyond_data(const std::vector<Eigen::Vector3d>& nodal, const std::vector<Eigen::Vector3d>& fixed,
                              const QualityGates& gates, nlohmann::json& report) {
  const auto largest = [](const std::vector<Eigen::Vector3d>& v) {
    double m = 0;
    for (const auto& x : v) m = std::max(m, x.norm());
    return m;
  };
  const double field = largest(nodal), data = largest(fixed);
  report["max_displacement_mm"] = field;
  report["max_prescribed_mm"] = data;
  if (field <= data + gates.max_unsupported_displacement_mm) return "";
  return "the elastic field moves " + std::to_string(field) + " mm where the matched surfaces move at most " +
         std::to_string(data) + " mm";
}

std::vector<Eigen::Vector3d> match_surfaces(const WarmState& warm, const IntraopDistanceMaps& maps,
                                            const Eigen::Matrix4d& A, const IntraopInput& input,
                                            const PipelineParameters& params, nlohmann::json& metrics,
                                            std::string* failure) {
  const auto& fixed = warm.fem.fixed_nodes();
  std::vector<Eigen::Vector3d> values(fixed.size(), Eigen::Vector3d::Zero());
  const bool intraop_has_ventricles =
      std::any_of(maps.ventricle_sdf_mm.voxels.begin(), maps.ventricle_sdf_mm.voxels.end(),
                  [](float d) { return d < 0.f; });
  const ImageF* image = input.t1 ? &*input.t1 : nullptr;
  // The surfaces are independent: each is matched in its own thread (the
  // outer surface dominates; the ventricles then come for free on the second
  // core). Results are gathered in surface order, so the outcome is the same
  // as a sequential run.
  std::vector<std::future<RepairedMatch>> matches(warm.surfaces.size());
  for (std::size_t i = 0; i < warm.surfaces.size(); ++i) {
    const auto& s = warm.surfaces[i];
    const bool outer = s.cavity_label == 0;
    if (!outer && !intraop_has_ventricles) continue;
    const ImageF& target = outer ? maps.outer_sdf_mm : maps.ventricle_sdf_mm;
    const auto& p = outer ? params.outer_surface : params.ventricle_surface;
    matches[i] = std::async(std::launch::async, [&s, &target, &p, &A, &params, image] {
      return match_and_repair(mapped_by_affine(s.surface, A), mapped_by_affine(s.contacts, A), target, p,
                              params.surface_repair, image, params.gates.max_unsupported_displacement_mm);
    });
  }
  for (std::size_t i = 0; i < warm.surfaces.size(); ++i) {
    const auto& s = warm.surfaces[i];
    nlohmann::json& m = metrics["surfaces"][s.name];
    if (!matches[i].valid()) {
      // No intraop data for this wall: it follows the affine (non-rigid 0) and
      // the metrics say so rather than inventing a match.
      m["matched"] = false;
      m["reason"] = "structure absent from the intraop labels";
      continue;
    }
    const RepairedMatch checked = matches[i].get();
    const SurfaceMatchResult& r = checked.match;
    for (std::size_t v = 0; v < s.surface.mesh_node.size(); ++v)
      values[warm.fixed_index_of_node[s.surface.mesh_node[v]]] = r.displacement_mm[v];
    m = {{"matched", true},
         {"vertices", s.surface.vertices_mm.size()},
         {"iterations", r.iterations},
         {"converged", r.converged},
         {"mean_residual_mm", r.mean_residual_mm},
         {"max_residual_mm", r.max_residual_mm},
         {"flipped_triangles", r.flipped_triangles},
         {"self_intersections", checked.repair.value("crossing_pairs_after", std::size_t{0})},
         {"repair", checked.repair}};
    if (!failure->empty()) continue;
    if (r.mean_residual_mm > params.gates.max_mean_surface_residual_mm)
      *failure = "surface match of " + s.name + " diverged (mean residual " + std::to_string(r.mean_residual_mm) + " mm)";
    else if (!checked.unsafe.empty())
      *failure = "surface match of " + s.name + " " + checked.unsafe;
  }
  return values;
}

}  // namespace brainshift
