#include "registration/active_surface.h"

#include <algorithm>
#include <array>
#include <optional>
#include <cmath>
#include <limits>
#include <sstream>

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "registration/linear_sampler.h"
#include "registration/surface_repair.h"
#include "image/resample.h"

namespace brainshift {
namespace {

using SpMat = Eigen::SparseMatrix<double>;
using Points = std::vector<Eigen::Vector3d>;

void validate(const TriSurface& s, const ImageF& target, const ActiveSurfaceParameters& p) {
  if (s.vertices_mm.empty() || s.triangles.empty()) {
    throw InputError("active surface: the surface has no vertices or no triangles");
  }
  const int n = static_cast<int>(s.vertices_mm.size());
  for (const auto& t : s.triangles)
    for (int v : t)
      if (v < 0 || v >= n) throw InputError("active surface: triangle refers to vertex " +
                                            std::to_string(v) + " of " + std::to_string(n));
  if (target.voxels.empty() || target.voxels.size() != target.grid.voxel_count()) {
    throw InputError("active surface: the target signed distance map is empty");
  }
  if (!(p.step > 0 && p.step <= 1) || !(p.membrane_stiffness >= 0) || p.max_iterations < 1 ||
      !(p.convergence_tolerance_mm > 0) || p.convergence_iterations < 1 || !(p.max_step_mm > 0) ||
      !(p.force_smoothing_mm >= 0) || !(p.edge_weight >= 0) || !(p.edge_search_mm > 0) ||
      !(p.contact_fraction > 0 && p.contact_fraction < 1) || !(p.capture_range_mm >= 0) ||
      p.stiffness_levels < 1 || p.stiffness_levels > 8 || !(p.stiffness_ratio >= 1) ||
      !(p.fold_guard.max_normal_turn_deg > 0 && p.fold_guard.max_normal_turn_deg < 90) ||
      !(p.fold_guard.min_area_ratio >= 0 && p.fold_guard.min_area_ratio < 1)) {
    throw InputError("active surface: invalid parameters (need 0 < step <= 1, stiffness >= 0, "
                     "positive tolerances, iterations and step clip, 0 < contact_fraction < 1, capture_range_mm >= 0, "
                     "1 <= stiffness_levels <= 8, stiffness_ratio >= 1, 0 < max_normal_turn_deg < 90, "
                     "0 <= min_area_ratio < 1)");
  }
}

// Lumped P1 mass (area/3 per vertex) and cotangent stiffness. Cotangents are
// clamped so that a needle triangle cannot dominate the operator.
void assemble_membrane(const TriSurface& s, Eigen::VectorXd* mass, SpMat* stiffness) {
  const int n = static_cast<int>(s.vertices_mm.size());
  std::vector<Eigen::Triplet<double>> trip;
  trip.reserve(s.triangles.size() * 12);
  *mass = Eigen::VectorXd::Zero(n);
  for (const auto& t : s.triangles) {
    const Eigen::Vector3d& a = s.vertices_mm[t[0]];
    const Eigen::Vector3d& b = s.vertices_mm[t[1]];
    const Eigen::Vector3d& c = s.vertices_mm[t[2]];
    const double twice_area = (b - a).cross(c - a).norm();
    if (!(twice_area > 1e-12)) continue;
    for (int v : t) (*mass)[v] += twice_area / 6.0;
    for (int corner = 0; corner < 3; ++corner) {
      const int k = t[corner], i = t[(corner + 1) % 3], j = t[(corner + 2) % 3];
      const Eigen::Vector3d ei = s.vertices_mm[i] - s.vertices_mm[k];
      const Eigen::Vector3d ej = s.vertices_mm[j] - s.vertices_mm[k];
      const double cot = std::clamp(ei.dot(ej) / twice_area, -20.0, 20.0);
      const double w = 0.5 * cot;
      trip.emplace_back(i, j, -w);
      trip.emplace_back(j, i, -w);
      trip.emplace_back(i, i, w);
      trip.emplace_back(j, j, w);
    }
  }
  // Vertices in no (valid) triangle: give them a typical mass so M stays positive.
  const double typical = mass->sum() / std::max(1, n);
  for (int v = 0; v < n; ++v)
    if (!((*mass)[v] > 0)) (*mass)[v] = typical > 0 ? typical : 1.0;
  stiffness->resize(n, n);
  stiffness->setFromTriplets(trip.begin(), trip.end());
}

double mean_edge_length(const TriSurface& s) {
  double sum = 0;
  for (const auto& t : s.triangles)
    for (int c = 0; c < 3; ++c) sum += (s.vertices_mm[t[c]] - s.vertices_mm[t[(c + 1) % 3]]).norm();
  return sum / (3.0 * s.triangles.size());
}

Points area_weighted_normals(const TriSurface& s, const Points& x) {
  Points n(x.size(), Eigen::Vector3d::Zero());
  for (const auto& t : s.triangles) {
    const Eigen::Vector3d fn = (x[t[1]] - x[t[0]]).cross(x[t[2]] - x[t[0]]);
    for (int v : t) n[v] += fn;
  }
  for (auto& v : n) {
    const double len = v.norm();
    if (len > 0) v /= len;
  }
  return n;
}

// Offset along the normal (mm, within +-search) of the strongest intensity
// step, by central differences on a 0.5 mm profile; 0 when the profile leaves
// the image. Runs for every vertex in every iteration, so it samples through a
// LinearSampler (affine inverted once) and keeps the profile on the stack.
double edge_offset_mm(const LinearSampler& image, const Eigen::Vector3d& x, const Eigen::Vector3d& n,
                      double search_mm) {
  constexpr double h = 0.5;
  constexpr int kMaxHalf = 64;
  const int half = std::min(kMaxHalf, static_cast<int>(std::ceil(search_mm / h)) + 1);
  std::array<double, 2 * kMaxHalf + 1> profile;
  for (int i = -half; i <= half; ++i)
    if (!image.sample(x + (i * h) * n, &profile[i + half], nullptr)) return 0.0;
  double best = 0, best_offset = 0;
  for (int i = -half + 1; i <= half - 1; ++i) {
    const double g = std::abs(profile[i + half + 1] - profile[i + half - 1]);
    if (g > best) best = g, best_offset = i * h;
  }
  return best_offset;
}

// Signed offset along n (mm) of the target's zero level: the first sign
// change of the distance map on the ray from x toward the surface (inward
// along -n when x is outside, d > 0), by 1 mm steps up to search_mm and linear
// interpolation; NaN when none is found. The distance map alone cannot pull a
// vertex into a narrow pit (a retractor's dent): over the pit's mouth the
// nearest surface is its wall, a few mm sideways, and the gradient points
// across the pit; along the normal the pit's floor is found.
double normal_crossing_mm(const LinearSampler& target, const Eigen::Vector3d& x, const Eigen::Vector3d& n, double d,
                          double search_mm) {
  const double sign = d > 0 ? -1.0 : 1.0;
  double prev = d;
  for (double s = 1.0; s <= search_mm + 1e-9; s += 1.0) {
    double cur;
    if (!target.sample(x + (sign * s) * n, &cur, nullptr)) break;
    if ((cur > 0) != (prev > 0)) return sign * (s - 1.0 + prev / (prev - cur));
    prev = cur;
  }
  return std::numeric_limits<double>::quiet_NaN();
}

struct ForceField {
  Points force;
  std::vector<char> has_data;
};

void force_at(std::size_t v, const Points& x, const Points& normals, const LinearSampler& target,
              const LinearSampler* image, const ActiveSurfaceParameters& p, ForceField& f) {
  double d;
  Eigen::Vector3d g;
  if (!target.sample(x[v], &d, &g)) return;
  const double len = g.norm();
  // Near the medial axis of the distance map the gradient vanishes and its
  // direction means nothing: no force there rather than a random one.
  if (len < 0.2) return;
  if (p.capture_range_mm > 0 && std::abs(d) > p.capture_range_mm) return;
  f.has_data[v] = 1;
  // Along the surface normal only, scaled by how well the normal agrees with
  // the distance gradient: the trilinear gradient direction jumps from cell
  // to cell, and letting those jumps push tangentially makes vertices drift
  // and chatter without changing the matched shape.
  const double alignment = std::max(0.0, normals[v].dot(g / len));
  f.force[v] = -d * alignment * normals[v];
  if (p.normal_search_mm > 0 && std::abs(d) > 0.5) {
    const double t = normal_crossing_mm(target, x[v], normals[v], d, p.normal_search_mm);
    if (std::isfinite(t) && std::abs(t) <= 3.0 * std::abs(d) + 1.0) f.force[v] = t * normals[v];
  }
  if (image && p.edge_weight > 0) {
    f.force[v] += p.edge_weight * edge_offset_mm(*image, x[v], normals[v], p.edge_search_mm) * normals[v];
  }
}

// Each vertex's force depends only on its own position and normal: the two
// halves of the vertices run side by side (the outer surface's match is the
// surface stage's critical path), with the same result on one core or two.
ForceField compute_force(const Points& x, const Points& normals, const LinearSampler& target,
                         const LinearSampler* image, const ActiveSurfaceParameters& p) {
  ForceField f{Points(x.size(), Eigen::Vector3d::Zero()), std::vector<char>(x.size(), 0)};
  parallel_halves(x.size(), 256, [&](std::size_t begin, std::size_t end) {
    for (std::size_t v = begin; v < end; ++v) force_at(v, x, normals, target, image, p, f);
  });
  return f;
}

// Explicit diffusion along the mesh: each pass (beta = 1/2 toward the neighbour
// mean) adds about h^2/4 of variance per axis, so 4 sigma^2 / h^2 passes
// approximate a Gaussian of width sigma.
void smooth_along_surface(Points* f, const std::vector<std::vector<int>>& nb, int passes) {
  Points tmp(f->size());
  for (int pass = 0; pass < passes; ++pass) {
    for (std::size_t v = 0; v < f->size(); ++v) {
      if (nb[v].empty()) {
        tmp[v] = (*f)[v];
        continue;
      }
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      for (int w : nb[v]) mean += (*f)[w];
      tmp[v] = 0.5 * (*f)[v] + 0.5 * mean / double(nb[v].size());
    }
    f->swap(tmp);
  }
}

// x = A^-1 b for the columns [c0, c1) of b, as SimplicialLDLT::solve does it
// (permute, unit-lower solve, divide by D, unit-upper solve, permute back)
// with the same operations in the same order for each column, but the
// columns side by side in each substitution: the factor is read once for
// all of them instead of once per column (the solves are memory-bound).
void solve_ldlt_columns(const Eigen::SimplicialLDLT<SpMat>& solver, const Eigen::MatrixXd& b, Eigen::Index c0,
                        Eigen::Index c1, Eigen::MatrixXd& out) {
  const Eigen::Index n = b.rows(), m = c1 - c0;
  if (m <= 0) return;
  const SpMat& L = solver.matrixL().nestedExpression();  // unit lower, column-major
  const Eigen::VectorXd& d = solver.vectorD();
  Eigen::MatrixXd x = solver.permutationP() * b.middleCols(c0, m);
  const int* start = L.outerIndexPtr();
  const int* row = L.innerIndexPtr();
  const double* value = L.valuePtr();
  const auto end_of = [&](Eigen::Index i) { return L.isCompressed() ? start[i + 1] : start[i] + L.innerNonZeroPtr()[i]; };
  for (Eigen::Index i = 0; i < n; ++i)  // L y = P b: column i of L updates the rows below i
    for (Eigen::Index c = 0, end = end_of(i); c < m; ++c) {
      const double t = x(i, c);
      if (t == 0.0) continue;
      for (int p = start[i]; p < end; ++p)
        if (row[p] > i) x(row[p], c) -= t * value[p];
    }
  for (Eigen::Index i = 0; i < n; ++i) {
    const double inverse = 1.0 / d[i];
    for (Eigen::Index c = 0; c < m; ++c) x(i, c) = inverse * x(i, c);
  }
  for (Eigen::Index i = n - 1; i >= 0; --i)  // L^T z = y: row i of L^T is column i of L
    for (Eigen::Index c = 0, end = end_of(i); c < m; ++c) {
      double t = x(i, c);
      for (int p = start[i]; p < end; ++p)
        if (row[p] > i) t -= value[p] * x(row[p], c);
      x(i, c) = t;
    }
  out.middleCols(c0, m) = solver.permutationPinv() * x;
}

// The three coordinates' membrane solves are independent: one on this core,
// two side by side on the other (solve_ldlt_columns), the same result.
Eigen::MatrixXd solve_columns(const Eigen::SimplicialLDLT<SpMat>& solver, const Eigen::MatrixXd& rhs) {
  Eigen::MatrixXd out(rhs.rows(), rhs.cols());
  parallel_halves(static_cast<std::size_t>(rhs.cols()), 1, [&](std::size_t begin, std::size_t end) {
    solve_ldlt_columns(solver, rhs, static_cast<Eigen::Index>(begin), static_cast<Eigen::Index>(end), out);
  });
  return out;
}

// Cuts back the approach of every facing-wall pair (see the header). Rows of
// u are vertex displacements.
void keep_walls_apart(Eigen::MatrixXd& u, const ContactPairs& contacts, double fraction) {
  for (int sweep = 0; sweep < 3; ++sweep) {
    bool changed = false;
    for (const ContactPair& c : contacts) {
      const Eigen::Vector3d d = c.direction_from_vertex;
      const double approach = (u.row(c.vertex) - u.row(c.facing)).dot(d.transpose());
      const double excess = approach - fraction * c.gap_mm;
      if (excess <= 0) continue;
      u.row(c.vertex) -= 0.5 * excess * d.transpose();
      u.row(c.facing) += 0.5 * excess * d.transpose();
      changed = true;
    }
    if (!changed) return;
  }
}

}  // namespace

SurfaceMatchResult match_surface(const TriSurface& surface, const ImageF& target_sdf,
                                 const ActiveSurfaceParameters& p, const ImageF* intraop_image,
                                 const ContactPairs* contacts) {
  validate(surface, target_sdf, p);
  if (contacts)
    for (const ContactPair& c : *contacts)
      if (c.vertex < 0 || c.facing < 0 || static_cast<std::size_t>(std::max(c.vertex, c.facing)) >= surface.vertices_mm.size())
        throw InputError("active surface: a contact pair refers to a vertex out of range");
  const Stopwatch clock;
  const std::size_t n = surface.vertices_mm.size();

  Eigen::VectorXd mass;
  SpMat stiffness;
  assemble_membrane(surface, &mass, &stiffness);
  SurfaceMatchResult r;
  const auto neighbours = surface_vertex_neighbours(surface);
  const double h = mean_edge_length(surface);
  const int smoothing_passes = std::min(
      20, static_cast<int>(std::lround(4 * p.force_smoothing_mm * p.force_smoothing_mm / (h * h))));
  const LinearSampler target(target_sdf);
  std::optional<LinearSampler> image_sampler;
  if (intraop_image && !intraop_image->voxels.empty()) image_sampler.emplace(*intraop_image);
  const LinearSampler* image = image_sampler ? &*image_sampler : nullptr;

  Eigen::MatrixXd u = Eigen::MatrixXd::Zero(n, 3);
  Points x = surface.vertices_mm;
  Points from(n), to(n);
  const FoldLimiter limiter(surface, p.fold_guard);
  // Every level's system has the membrane's pattern: its ordering and
  // elimination tree are worked out once, each level factorises its values
  // (the same factors as a full compute() per level).
  Eigen::SimplicialLDLT<SpMat> solver;
  for (int level = 0; level < p.stiffness_levels; ++level) {
    const double alpha = p.membrane_stiffness * std::pow(p.stiffness_ratio, p.stiffness_levels - 1 - level);
    SpMat system = p.step * alpha * stiffness;
    system.diagonal() += mass;
    if (level == 0) solver.analyzePattern(system);
    solver.factorize(system);
    if (solver.info() != Eigen::Success) {
      r.displacement_mm.assign(n, Eigen::Vector3d::Zero());
      r.message = "failed: membrane matrix factorisation failed (degenerate surface?)";
      return r;
    }
    // Each level's membrane penalises only what it adds to the previous
    // levels' result (iterated Tikhonov): the wide motion a stiff level found
    // is not pulled back by the softer ones, so a 25 mm sink is not biased
    // toward the start by the final stiffness, and each level smooths only
    // the detail it adds.
    const Eigen::MatrixXd base_term = (p.step * alpha) * (stiffness * u);
    int quiet = 0;
    r.converged = false;
    for (int it = 0; it < p.max_iterations; ++it) {
      // The normals at x serve the forces and, below, the convergence test.
      const Points normals = area_weighted_normals(surface, x);
      ForceField f = compute_force(x, normals, target, image, p);
      smooth_along_surface(&f.force, neighbours, smoothing_passes);
      Eigen::MatrixXd rhs = u;
      for (std::size_t v = 0; v < n; ++v) {
        Eigen::Vector3d step = p.step * f.force[v];
        const double len = step.norm();
        if (len > p.max_step_mm) step *= p.max_step_mm / len;
        rhs.row(v) += step.transpose();
      }
      rhs = mass.asDiagonal() * rhs;
      if (level > 0) rhs += base_term;
      Eigen::MatrixXd u_new = solve_columns(solver, rhs);
      if (contacts) keep_walls_apart(u_new, *contacts, p.contact_fraction);
      if (!u_new.allFinite()) {
        u = u_new;
        break;
      }
      if (p.fold_guard_enabled) {
        for (std::size_t v = 0; v < n; ++v) from[v] = u.row(v).transpose(), to[v] = u_new.row(v).transpose();
        r.guarded_vertices_last = limiter.limit(from, to);
        r.guarded_vertices_max = std::max(r.guarded_vertices_max, r.guarded_vertices_last);
        for (std::size_t v = 0; v < n; ++v) u_new.row(v) = to[v].transpose();
      }
      ++r.iterations;
      // Convergence looks at the update along the current vertex normals: that
      // is the matched shape. Tangential motion keeps relaxing slowly afterwards
      // (normal forces give the membrane no tangential pull, so smooth tangential
      // modes decay only at the rate 1/(1 + alpha k^2)); it slides vertices along
      // the surface without changing it.
      double update = 0;
      for (std::size_t v = 0; v < n; ++v)
        update = std::max(update, std::abs(normals[v].dot((u_new.row(v) - u.row(v)).transpose())));
      u = u_new;
      for (std::size_t v = 0; v < n; ++v) x[v] = surface.vertices_mm[v] + u.row(v).transpose();
      quiet = update < p.convergence_tolerance_mm ? quiet + 1 : 0;
      if (quiet >= p.convergence_iterations) {
        r.converged = true;
        break;
      }
    }
    if (!u.allFinite()) break;
  }

  r.displacement_mm.resize(n);
  r.residual_distance_mm.assign(n, std::numeric_limits<double>::quiet_NaN());
  double sum = 0;
  std::size_t with_data = 0;
  for (std::size_t v = 0; v < n; ++v) {
    r.displacement_mm[v] = u.row(v).transpose();
    double d;
    Eigen::Vector3d g;
    if (!target.sample(x[v], &d, &g)) continue;
    r.residual_distance_mm[v] = std::abs(d);
    sum += std::abs(d);
    r.max_residual_mm = std::max(r.max_residual_mm, std::abs(d));
    ++with_data;
  }
  r.vertices_without_data = n - with_data;
  r.mean_residual_mm = with_data ? sum / double(with_data) : 0.0;
  r.flipped_triangles = flipped_triangles(surface, x).size();
  r.seconds = clock.seconds();

  std::ostringstream msg;
  msg.precision(3);
  msg << (r.converged ? "converged" : "not converged (iteration limit)") << " after "
      << r.iterations << " iterations; mean residual " << r.mean_residual_mm << " mm, max "
      << r.max_residual_mm << " mm";
  if (r.vertices_without_data) msg << "; " << r.vertices_without_data << " vertices outside the target image";
  if (r.flipped_triangles) msg << "; " << r.flipped_triangles << " flipped triangles (folded surface)";
  if (r.guarded_vertices_last) msg << "; fold guard held " << r.guarded_vertices_last << " vertices";
  if (with_data == 0) msg << "; no vertex lies inside the target image";
  r.message = msg.str();
  return r;
}

}  // namespace brainshift
