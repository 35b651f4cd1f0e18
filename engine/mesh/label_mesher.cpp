// The only translation unit that includes CGAL (slow to compile; sequential
// Mesh_3 only: the parallel mesher was faster but left 9x more bad tets).
#include "mesh/label_mesher.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Image_3.h>
#include <CGAL/Labeled_mesh_domain_3.h>
#include <CGAL/Mesh_complex_3_in_triangulation_3.h>
#include <CGAL/Mesh_criteria_3.h>
#include <CGAL/Mesh_3/Slivers_exuder.h>
#include <CGAL/Mesh_3/min_dihedral_angle.h>
#include <CGAL/Mesh_3/sliver_criteria.h>
#include <CGAL/Mesh_error_code.h>
#include <CGAL/Mesh_triangulation_3.h>
#include <CGAL/Random.h>
#include <CGAL/perturb_mesh_3.h>
#include <CGAL/refine_mesh_3.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <queue>
#include <string>

#include "core/errors.h"
#include "core/timer.h"
#include "mesh/mesh_assembly.h"

namespace brainshift {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Domain = CGAL::Labeled_mesh_domain_3<Kernel>;
using Tr = CGAL::Mesh_triangulation_3<Domain, CGAL::Default, CGAL::Sequential_tag>::type;
using C3t3 = CGAL::Mesh_complex_3_in_triangulation_3<Tr>;
using Criteria = CGAL::Mesh_criteria_3<Tr>;
using Point = Tr::Bare_point;

constexpr int kPad = 1;            // zero voxels around the image so every surface closes
// CGAL subdomains: 1 all tissue; cavity i -> 2 + i; interface label j ->
// 2 + (number of cavities) + j.
constexpr unsigned char kTissue = 1;

void validate(const LabelImage& labels, const MeshingParameters& p) {
  const auto& d = labels.grid.dims;
  if (d[0] < 1 || d[1] < 1 || d[2] < 1 || labels.voxels.size() != labels.grid.voxel_count())
    throw InputError("mesh_label_image: label image has invalid dimensions or voxel count");
  if (std::abs(labels.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) < 1e-12)
    throw InputError("mesh_label_image: world_from_voxel is singular");
  auto positive = [](double v, const char* name) {
    if (!(v > 0) || !std::isfinite(v))
      throw InputError(std::string("mesh_label_image: parameter ") + name + " must be > 0");
  };
  positive(p.facet_angle_deg, "facet_angle_deg");
  positive(p.facet_size_mm, "facet_size_mm");
  positive(p.facet_distance_mm, "facet_distance_mm");
  positive(p.cell_size_mm, "cell_size_mm");
  positive(p.cell_radius_edge_ratio, "cell_radius_edge_ratio");
  if (!(p.exude_steps_per_vertex >= 0) || !std::isfinite(p.exude_steps_per_vertex))
    throw InputError("mesh_label_image: parameter exude_steps_per_vertex must be >= 0 and finite");
  if (p.facet_angle_deg > 30)
    throw InputError("mesh_label_image: facet_angle_deg > 30 may not terminate (CGAL bound)");
  if (p.cavity_labels.size() + p.interface_labels.size() > 250)
    throw InputError("mesh_label_image: too many cavity and interface labels (max 250)");
  for (auto c : p.cavity_labels)
    if (c == 0 || c == p.default_tissue_label)
      throw InputError("mesh_label_image: cavity label must differ from 0 and the tissue label");
  for (auto c : p.interface_labels)
    if (c == 0 || c == p.default_tissue_label ||
        std::find(p.cavity_labels.begin(), p.cavity_labels.end(), c) != p.cavity_labels.end())
      throw InputError("mesh_label_image: interface label must differ from 0, the tissue label and the cavities");
}

// Subdomain value of each label (see kTissue).
std::vector<unsigned char> subdomain_of_label(const MeshingParameters& p) {
  std::vector<unsigned char> s(65536, kTissue);
  s[0] = 0;
  for (std::size_t i = 0; i < p.cavity_labels.size(); ++i) s[p.cavity_labels[i]] = static_cast<unsigned char>(2 + i);
  for (std::size_t j = 0; j < p.interface_labels.size(); ++j)
    s[p.interface_labels[j]] = static_cast<unsigned char>(2 + p.cavity_labels.size() + j);
  return s;
}

// Padded subdomain image (values: subdomain_of_label). Voxel (i,j,k) of the
// input sits at (i*sx, j*sy, k*sz) in CGAL space.
CGAL::Image_3 make_subdomain_image(const LabelImage& labels, const MeshingParameters& p,
                                   const Eigen::Vector3d& spacing, bool* has_tissue) {
  const std::vector<unsigned char> subdomain = subdomain_of_label(p);
  const std::size_t cavity_count = p.cavity_labels.size();
  const auto& d = labels.grid.dims;
  const std::size_t nx = d[0] + 2 * kPad, ny = d[1] + 2 * kPad, nz = d[2] + 2 * kPad;
  _image* im = ::_createImage(nx, ny, nz, 1, spacing.x(), spacing.y(), spacing.z(), 1,
                              WK_FIXED, SGN_UNSIGNED);
  if (!im) throw ComputeError("mesh_label_image: could not allocate the CGAL image");
  im->tx = static_cast<float>(-kPad * spacing.x());
  im->ty = static_cast<float>(-kPad * spacing.y());
  im->tz = static_cast<float>(-kPad * spacing.z());
  auto* data = static_cast<unsigned char*>(im->data);
  std::fill(data, data + nx * ny * nz, 0);
  *has_tissue = false;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        const std::uint16_t l = labels.at(i, j, k);
        if (l == 0) continue;
        const unsigned char s = subdomain[l];
        *has_tissue |= (s == kTissue || s >= 2 + cavity_count);
        data[(i + kPad) + nx * ((j + kPad) + ny * static_cast<std::size_t>(k + kPad))] = s;
      }
  return CGAL::Image_3(im);
}

struct Component {
  std::array<int, 3> seed;  // padded voxel index nearest the component's centroid
  std::array<int, 3> lo, hi;
};

// 6-connected components of every non-zero subdomain value.
std::vector<Component> find_components(const CGAL::Image_3& image) {
  const int nx = static_cast<int>(image.xdim()), ny = static_cast<int>(image.ydim()),
            nz = static_cast<int>(image.zdim());
  const auto* data = static_cast<const unsigned char*>(image.data());
  auto idx = [&](int i, int j, int k) { return i + std::size_t(nx) * (j + std::size_t(ny) * k); };
  std::vector<char> seen(std::size_t(nx) * ny * nz, 0);
  std::vector<Component> out;
  std::vector<std::array<int, 3>> members;
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const unsigned char v = data[idx(i, j, k)];
        if (v == 0 || seen[idx(i, j, k)]) continue;
        members.clear();
        std::queue<std::array<int, 3>> q;
        q.push({i, j, k});
        seen[idx(i, j, k)] = 1;
        Eigen::Vector3d sum = Eigen::Vector3d::Zero();
        Component c{{i, j, k}, {i, j, k}, {i, j, k}};
        while (!q.empty()) {
          const auto p = q.front();
          q.pop();
          members.push_back(p);
          sum += Eigen::Vector3d(p[0], p[1], p[2]);
          for (int a = 0; a < 3; ++a) {
            c.lo[a] = std::min(c.lo[a], p[a]);
            c.hi[a] = std::max(c.hi[a], p[a]);
          }
          static constexpr int off[6][3] = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}};
          for (const auto& o : off) {
            const int a = p[0] + o[0], b = p[1] + o[1], e = p[2] + o[2];
            if (a < 0 || b < 0 || e < 0 || a >= nx || b >= ny || e >= nz) continue;
            const std::size_t n = idx(a, b, e);
            if (seen[n] || data[n] != v) continue;
            seen[n] = 1;
            q.push({a, b, e});
          }
        }
        const Eigen::Vector3d centroid = sum / double(members.size());
        double best = 1e300;
        for (const auto& m : members) {
          const double d2 = (Eigen::Vector3d(m[0], m[1], m[2]) - centroid).squaredNorm();
          if (d2 < best) best = d2, c.seed = m;
        }
        out.push_back(c);
      }
  return out;
}

// Why: CGAL's default initial points come from random rays through the whole
// domain and can miss small interior components (the ventricles were meshed as
// solid tissue). Like CGAL's initialize_triangulation_from_labeled_image, we
// put surface points around every component, but with fixed directions (no
// time-seeded randomness) and without printing to stdout.
std::size_t seed_every_component(C3t3& c3t3, const Domain& domain, const CGAL::Image_3& image) {
  const auto components = find_components(image);
  const double v[3] = {image.vx(), image.vy(), image.vz()};
  const double t[3] = {image.tx(), image.ty(), image.tz()};
  Tr& tr = c3t3.triangulation();
  auto intersect = domain.construct_intersection_object();
  auto to_point = [&](const std::array<double, 3>& ijk) {
    return Point(ijk[0] * v[0] + t[0], ijk[1] * v[1] + t[1], ijk[2] * v[2] + t[2]);
  };
  for (const auto& c : components) {
    double reach = 2;  // voxels: enough to leave the component's bounding box
    for (int a = 0; a < 3; ++a) reach += c.hi[a] - c.lo[a];
    for (int dx = -1; dx <= 1; ++dx)
      for (int dy = -1; dy <= 1; ++dy)
        for (int dz = -1; dz <= 1; ++dz) {
          if (dx == 0 && dy == 0 && dz == 0) continue;
          const Point from = to_point({double(c.seed[0]), double(c.seed[1]), double(c.seed[2])});
          const Point to = to_point({c.seed[0] + reach * dx, c.seed[1] + reach * dy, c.seed[2] + reach * dz});
          const auto hit = intersect(Tr::Geom_traits::Segment_3(from, to));
          if (std::get<2>(hit) == 0) continue;
          const auto wp = tr.geom_traits().construct_weighted_point_3_object()(std::get<0>(hit));
          Tr::Locate_type lt;
          int li, lj;
          tr.locate(wp, lt, li, lj);
          if (lt == Tr::VERTEX) continue;
          const auto vh = tr.insert(wp);
          if (vh == Tr::Vertex_handle()) continue;
          c3t3.set_dimension(vh, 2);  // by construction on a surface patch
          c3t3.set_index(vh, std::get<1>(hit));
        }
  }
  if (tr.dimension() != 3)
    throw ComputeError("mesh_label_image: too few surface points to start meshing (image too small?)");
  return components.size();
}

// The most vertices the criteria can justify: a mesh as fine everywhere as the
// finest size any criterion asks for (facet size, cell size or facet
// distance: a facet narrower than the distance tolerance cannot deviate from
// the surface by more than it), one vertex per s^3 of labelled volume and per
// s^2 of labelled surface (the voxel staircase, which overestimates the true
// area), plus the seed points. Refinement that reaches it is chasing detail
// finer than every requested size (noise, specks, a staircase of thick
// slices); it is stopped there rather than left to grow without bound.
std::size_t refinement_vertex_cap(const CGAL::Image_3& image, const MeshingParameters& p,
                                  std::size_t seed_points) {
  const std::size_t nx = image.xdim(), ny = image.ydim(), nz = image.zdim();
  const auto* data = static_cast<const unsigned char*>(image.data());
  const double vx = image.vx(), vy = image.vy(), vz = image.vz();
  std::size_t labelled = 0, faces_x = 0, faces_y = 0, faces_z = 0;
  for (std::size_t k = 0; k < nz; ++k)
    for (std::size_t j = 0; j < ny; ++j)
      for (std::size_t i = 0; i < nx; ++i) {
        const std::size_t n = i + nx * (j + ny * k);
        labelled += data[n] != 0;
        if (i + 1 < nx) faces_x += data[n] != data[n + 1];
        if (j + 1 < ny) faces_y += data[n] != data[n + nx];
        if (k + 1 < nz) faces_z += data[n] != data[n + nx * ny];
      }
  const double volume_mm3 = labelled * vx * vy * vz;
  const double area_mm2 = faces_x * vy * vz + faces_y * vx * vz + faces_z * vx * vy;
  const double s = std::min({p.facet_size_mm, p.cell_size_mm, p.facet_distance_mm});
  return seed_points + static_cast<std::size_t>(std::ceil(volume_mm3 / (s * s * s) + area_mm2 / (s * s)));
}

using SliverCriterion = CGAL::Mesh_3::Min_dihedral_angle_criterion<Tr>;

// Smallest dihedral angle of the meshed cells and how many are below bound_deg.
std::pair<double, std::size_t> dihedral_summary(const C3t3& c3t3, double bound_deg) {
  double min_deg = 180;
  std::size_t below = 0;
  const Tr& tr = c3t3.triangulation();
  for (auto c = c3t3.cells_in_complex_begin(); c != c3t3.cells_in_complex_end(); ++c) {
    const double a = CGAL::to_double(CGAL::Mesh_3::minimum_dihedral_angle(tr.tetrahedron(c), tr.geom_traits()));
    min_deg = std::min(min_deg, a);
    below += a < bound_deg;
  }
  return {min_deg, below};
}

// Thrown by the visitor to leave CGAL's exudation loop when the budget is
// spent. The visitor runs at the end of a loop step, when the triangulation
// is consistent: the same state CGAL's own time limit stops in.
struct ExudeBudgetSpent {};

class ExudeBudget {
 public:
  ExudeBudget(std::size_t budget, std::size_t* steps) : budget_(budget), steps_(steps) {}
  void after_cell_pumped(std::size_t cells_left) const {
    if (++*steps_ >= budget_ && cells_left > 0) throw ExudeBudgetSpent{};
  }

 private:
  std::size_t budget_;
  std::size_t* steps_;
};

// CGAL's sliver exudation (what exude_mesh_3 runs) with a budget of queue
// steps instead of a time limit: bounded, and the result depends only on the
// input. Fills the exudation fields of stats.
void exude_with_budget(C3t3& c3t3, const MeshingParameters& p, MeshingStats& stats) {
  const double bound = p.exude_sliver_bound_deg > 0 ? p.exude_sliver_bound_deg : 90.0;
  std::tie(stats.min_dihedral_before_deg, stats.slivers_before) = dihedral_summary(c3t3, bound);
  stats.exude_budget = static_cast<std::size_t>(
      std::ceil(p.exude_steps_per_vertex * static_cast<double>(c3t3.triangulation().number_of_vertices())));
  stats.exude_steps = 0;
  stats.exude_budget_hit = false;
  if (stats.exude_budget > 0) {
    SliverCriterion criterion(p.exude_sliver_bound_deg, c3t3.triangulation());
    CGAL::Mesh_3::Slivers_exuder<C3t3, SliverCriterion, ExudeBudget> exuder(c3t3, criterion);
    try {
      exuder(ExudeBudget(stats.exude_budget, &stats.exude_steps));
    } catch (const ExudeBudgetSpent&) {
      stats.exude_budget_hit = true;
    }
  }
  std::tie(stats.min_dihedral_after_deg, stats.slivers_after) = dihedral_summary(c3t3, bound);
}

RawTetMesh extract_tissue(const C3t3& c3t3, const LabelImage& labels, const Eigen::Vector3d& spacing,
                          const MeshingParameters& p) {
  const auto& cavities = p.cavity_labels;
  const int first_interface = 2 + static_cast<int>(cavities.size());
  // Tissue and interface subdomains are kept; the rest is outside or cavity.
  auto kept = [&](int s) { return s == kTissue || s >= first_interface; };
  RawTetMesh raw;
  std::map<Tr::Vertex_handle, int> node_of;
  // world = world_from_voxel * (p / spacing): CGAL space is index * spacing.
  Eigen::Matrix4d world_from_cgal = labels.grid.world_from_voxel;
  world_from_cgal.topLeftCorner<3, 3>() *= spacing.cwiseInverse().asDiagonal();
  const Tr& tr = c3t3.triangulation();
  for (auto v = tr.finite_vertices_begin(); v != tr.finite_vertices_end(); ++v) {
    const auto& p = tr.point(v);
    node_of.emplace(v, static_cast<int>(raw.nodes_mm.size()));
    raw.nodes_mm.push_back((world_from_cgal * Eigen::Vector4d(p.x(), p.y(), p.z(), 1)).head<3>());
  }
  auto subdomain = [&](Tr::Cell_handle c) -> int {
    return c3t3.is_in_complex(c) ? static_cast<int>(c3t3.subdomain_index(c)) : 0;
  };
  for (auto c = c3t3.cells_in_complex_begin(); c != c3t3.cells_in_complex_end(); ++c) {
    const int own = subdomain(c);
    if (!kept(own)) continue;
    const int tet = static_cast<int>(raw.tets.size());
    raw.tets.push_back({node_of.at(c->vertex(0)), node_of.at(c->vertex(1)),
                        node_of.at(c->vertex(2)), node_of.at(c->vertex(3))});
    raw.forced_labels.push_back(own >= first_interface ? p.interface_labels.at(own - first_interface) : -1);
    for (int f = 0; f < 4; ++f) {
      const int other = subdomain(c->neighbor(f));
      if (kept(other)) continue;
      const int label = other == 0 ? 0 : cavities.at(other - 2);
      raw.boundary.push_back({tet, f, label});
    }
  }
  return raw;
}

}  // namespace

TetMesh mesh_label_image(const LabelImage& labels, const MeshingParameters& params, MeshingStats* stats_out,
                         const MeshingProgressFn& progress) {
  validate(labels, params);
  Stopwatch total, stage;
  const Eigen::Vector3d spacing = labels.grid.spacing_mm();
  bool has_tissue = false;
  CGAL::Image_3 image = make_subdomain_image(labels, params, spacing, &has_tissue);
  if (!has_tissue) throw InputError("mesh_label_image: label image has no tissue voxels");

  CGAL::Random rng(params.random_seed);
  namespace P = CGAL::parameters;
  const Domain domain = Domain::create_labeled_image_mesh_domain(image, P::p_rng = &rng);
  const Criteria criteria(P::facet_angle = params.facet_angle_deg, P::facet_size = params.facet_size_mm,
                          P::facet_distance = params.facet_distance_mm,
                          P::cell_radius_edge_ratio = params.cell_radius_edge_ratio,
                          P::cell_size = params.cell_size_mm);
  MeshingStats stats;
  C3t3 c3t3;
  stats.seed_components = seed_every_component(c3t3, domain, image);
  stats.vertex_cap = params.max_vertices > 0
                         ? params.max_vertices
                         : refinement_vertex_cap(image, params, c3t3.triangulation().number_of_vertices());
  CGAL::Mesh_error_code refine_error = CGAL::CGAL_MESH_3_NO_ERROR;
  CGAL::refine_mesh_3(c3t3, domain, criteria, P::no_perturb(), P::no_exude(),
                      P::mesh_3_options(P::maximal_number_of_vertices = stats.vertex_cap,
                                        P::pointer_to_error_code = &refine_error));
  stats.refined_vertices = c3t3.triangulation().number_of_vertices();
  if (refine_error == CGAL::CGAL_MESH_3_MAXIMAL_NUMBER_OF_VERTICES_REACHED)
    throw ComputeError("mesh_label_image: refinement stopped at its cap of " + std::to_string(stats.vertex_cap) +
                       " vertices (a mesh as fine everywhere as the finest requested size): the label map has "
                       "detail finer than the mesh sizes (specks, noise, a staircase of thick slices); smooth or "
                       "clean the labels, or mesh with larger sizes");
  stats.seconds_refine = stage.lap();
  if (progress) progress("refine", stats);
  if (params.optimise) {
    if (params.perturb)
      CGAL::perturb_mesh_3(c3t3, domain, P::time_limit = 0, P::sliver_bound = params.perturb_sliver_bound_deg);
    exude_with_budget(c3t3, params, stats);
  }
  stats.seconds_optimise = stage.lap();
  if (progress) progress("exude", stats);

  RawTetMesh raw = extract_tissue(c3t3, labels, spacing, params);
  if (raw.tets.empty()) throw ComputeError("mesh_label_image: CGAL produced no tissue tetrahedra");
  AssemblyOptions options;
  options.cavity_labels = params.cavity_labels;
  options.interface_labels = params.interface_labels;
  options.default_tissue_label = params.default_tissue_label;
  options.keep_largest_component = params.keep_largest_component;
  AssemblyReport report;
  TetMesh mesh = assemble_tet_mesh(std::move(raw), labels, options, &report);
  stats.dropped_degenerate = report.dropped_degenerate;
  stats.dropped_island_tets = report.dropped_island_tets;
  stats.seconds_total = total.seconds();
  if (stats_out) *stats_out = stats;
  return mesh;
}

}  // namespace brainshift
