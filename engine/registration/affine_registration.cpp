#include "registration/affine_registration.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <sstream>
#include <thread>
#include <utility>

#include <Eigen/Eigenvalues>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/pose_sweep.h"
#include "core/rotation_angle.h"
#include "registration/linear_sampler.h"

namespace brainshift {
namespace {

using Vec12 = Eigen::Matrix<double, 12, 1>;
using Mat12 = Eigen::Matrix<double, 12, 12>;

// x = B q + t with q = (p - centre) / radius: the normalisation makes the 9
// linear parameters and the 3 translations comparable (all in mm of motion at
// the typical point), which keeps the 12x12 normal equations well conditioned.
struct AffineState {
  Eigen::Matrix3d B = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
};

struct Term {
  std::vector<Eigen::Vector3d> q;  // normalised preop points of this level
  const ImageF* sdf = nullptr;
  double weight = 0;               // structure weight / point count
};

struct Evaluation {
  double cost = 0;
  std::size_t valid = 0, total = 0, inliers = 0;
  double sum_squares = 0;
  Mat12 H = Mat12::Zero();
  Vec12 b = Vec12::Zero();
};

// Geman-McClure: rho(r) = (c^2/2) r^2 / (c^2 + r^2); IRLS weight rho'(r)/r.
double gm_rho(double r, double c) { return 0.5 * c * c * r * r / (c * c + r * r); }
double gm_weight(double r, double c) {
  const double d = c * c + r * r;
  return c * c * c * c / (d * d);
}

// Accumulates the points [begin(n), end(n)) of every term, n = term size.
template <class Range>
void accumulate(const std::vector<Term>& terms, const AffineState& s, double c, Range range, Evaluation& e) {
  for (const Term& term : terms) {
    const LinearSampler sampler(*term.sdf);
    const auto [begin, end] = range(term.q.size());
    for (std::size_t i = begin; i < end; ++i) {
      const Eigen::Vector3d& q = term.q[i];
      ++e.total;
      const Eigen::Vector3d x = s.B * q + s.t;
      double r;
      Eigen::Vector3d g;
      if (!sampler.sample(x, &r, &g)) {
        e.cost += term.weight * 0.5 * c * c;  // saturated loss: see header
        continue;
      }
      ++e.valid;
      e.sum_squares += r * r;
      if (std::abs(r) < 2 * c) ++e.inliers;
      e.cost += term.weight * gm_rho(r, c);
      Vec12 J;
      J << g.x() * q, g.y() * q, g.z() * q, g;
      const double w = term.weight * gm_weight(r, c);
      e.H.selfadjointView<Eigen::Lower>().rankUpdate(J, w);
      e.b += w * r * J;
    }
  }
}

// Two partial sums over fixed halves of every term's points, added in a fixed
// order: the same numbers whether one thread or two compute them (the second
// core is idle during the intraop stages at one MPI rank).
Evaluation evaluate(const std::vector<Term>& terms, const AffineState& s, double c) {
  std::array<Evaluation, 2> part;
  // Each half sums into its own and stores it once: the two parts are
  // adjacent, and the end of one shares a cache line with the start of the other.
  auto half = [&](int h) {
    Evaluation own;
    accumulate(terms, s, c, [h](std::size_t n) { return h == 0 ? std::pair{std::size_t{0}, n / 2} : std::pair{n / 2, n}; },
               own);
    part[h] = own;
  };
  std::size_t points = 0;
  for (const Term& term : terms) points += term.q.size();
  if (std::thread::hardware_concurrency() >= 2 && points >= 4000) {
    std::thread helper(half, 1);
    half(0);
    helper.join();
  } else {
    half(0);
    half(1);
  }
  Evaluation e = part[0];
  e.cost += part[1].cost;
  e.valid += part[1].valid;
  e.total += part[1].total;
  e.inliers += part[1].inliers;
  e.sum_squares += part[1].sum_squares;
  e.H += part[1].H;
  e.b += part[1].b;
  const Mat12 full = e.H.selfadjointView<Eigen::Lower>();
  e.H = full;
  return e;
}

AffineState apply_update(const AffineState& s, const Vec12& delta) {
  AffineState n = s;
  for (int row = 0; row < 3; ++row) n.B.row(row) += delta.segment<3>(3 * row).transpose();
  n.t += delta.tail<3>();
  return n;
}

double max_motion_mm(const std::vector<Term>& terms, const Vec12& delta) {
  const AffineState zero{Eigen::Matrix3d::Zero(), Eigen::Vector3d::Zero()};
  const AffineState d = apply_update(zero, delta);
  double m = 0;
  for (const Term& term : terms)
    for (const auto& q : term.q) m = std::max(m, (d.B * q + d.t).norm());
  return m;
}

struct LevelOutcome {
  AffineState state;
  Evaluation eval;
  int iterations = 0;
  bool converged = false;  // the last proposed step was below the level's tolerance
};

// Rigid motion plus isotropic scale: 7 parameters (rotation vector w, log
// scale sigma, translation), applied as B <- e^sigma R(w) B, t <- t + dt. A
// similarity cannot bend or shear, so a local sink (a part of the outline
// 20-25 mm away from the rest) can shift it only by what moves the whole
// outline: the sink's points then saturate the robust loss instead of
// shearing the fit toward them.
enum class Model { similarity, affine };

// d(12 affine parameters) / d(w, sigma, dt): dB = (sigma I + [w]x) B.
Eigen::Matrix<double, 12, 7> similarity_basis(const Eigen::Matrix3d& B) {
  Eigen::Matrix<double, 12, 7> P = Eigen::Matrix<double, 12, 7>::Zero();
  for (int g = 0; g < 4; ++g) {
    Eigen::Matrix3d G = Eigen::Matrix3d::Zero();
    if (g < 3) {
      Eigen::Vector3d w = Eigen::Vector3d::Zero();
      w[g] = 1;
      G << 0, -w.z(), w.y(), w.z(), 0, -w.x(), -w.y(), w.x(), 0;
    } else {
      G = Eigen::Matrix3d::Identity();
    }
    const Eigen::Matrix3d dB = G * B;
    for (int row = 0; row < 3; ++row) P.block<3, 1>(3 * row, g) = dB.row(row).transpose();
  }
  P.block<3, 3>(9, 4).setIdentity();
  return P;
}

AffineState apply_similarity(const AffineState& s, const Eigen::Matrix<double, 7, 1>& d) {
  AffineState n = s;
  const Eigen::Vector3d w = d.head<3>();
  const Eigen::Matrix3d R = w.norm() > 0 ? Eigen::AngleAxisd(w.norm(), w.normalized()).toRotationMatrix()
                                         : Eigen::Matrix3d::Identity();
  n.B = std::exp(d[3]) * R * s.B;
  n.t += d.tail<3>();
  return n;
}

// Levenberg-Marquardt on the IRLS normal equations of the model; a step is
// kept only when the robust cost decreases. Bounded by max_iterations.
LevelOutcome run_level(const std::vector<Term>& terms, AffineState state, double c, Model model,
                       int max_iterations, double tolerance_mm) {
  LevelOutcome out;
  Evaluation eval = evaluate(terms, state, c);
  double mu = 1e-3;
  for (int it = 0; it < max_iterations && eval.valid >= 12; ++it) {
    ++out.iterations;
    Vec12 delta;
    AffineState trial;
    if (model == Model::affine) {
      Mat12 A = eval.H;
      A.diagonal() += mu * eval.H.diagonal() + Vec12::Constant(1e-12 * eval.H.diagonal().maxCoeff());
      delta = -A.ldlt().solve(eval.b);
      trial = apply_update(state, delta);
    } else {
      const Eigen::Matrix<double, 12, 7> P = similarity_basis(state.B);
      const Eigen::Matrix<double, 7, 7> H = P.transpose() * eval.H * P;
      Eigen::Matrix<double, 7, 7> A = H;
      A.diagonal() += mu * H.diagonal() + Eigen::Matrix<double, 7, 1>::Constant(1e-12 * H.diagonal().maxCoeff());
      const Eigen::Matrix<double, 7, 1> d = -A.ldlt().solve(P.transpose() * eval.b);
      delta = P * d;
      trial = apply_similarity(state, d);
    }
    if (!delta.allFinite()) break;
    const double motion = max_motion_mm(terms, delta);
    Evaluation trial_eval = evaluate(terms, trial, c);
    if (trial_eval.cost < eval.cost) {
      state = trial;
      eval = std::move(trial_eval);
      mu = std::max(mu / 3, 1e-7);
    } else {
      mu *= 4;
    }
    // The proposed step is below tolerance: further progress is below what the
    // voxelised data can resolve, whether or not this step was accepted.
    if (motion < tolerance_mm) {
      out.converged = true;
      break;
    }
    if (mu > 1e8) break;  // no descent direction left: stalled at a minimum of this cost
  }
  out.state = state;
  out.eval = std::move(eval);
  return out;
}

// Robust spread of the signed distances at the state: 1.4826 x the median
// absolute residual (the normal-consistent MAD about 0, the fit's target),
// over the points inside the intraop grid. Up to half the outline may be
// anything (a sink, a retractor, a missing lobe) without moving it.
double mad_sigma_mm(const std::vector<Term>& terms, const AffineState& s) {
  std::vector<double> r;
  for (const Term& term : terms) {
    const LinearSampler sampler(*term.sdf);
    for (const auto& q : term.q) {
      double d;
      if (sampler.sample(s.B * q + s.t, &d, nullptr)) r.push_back(std::abs(d));
    }
  }
  if (r.empty()) return 0;
  auto mid = r.begin() + r.size() / 2;
  std::nth_element(r.begin(), mid, r.end());
  return 1.4826 * *mid;
}

// Subsample sizes: geometric from coarse to fine.
std::size_t level_points(const AffineRegistrationParameters& p, int level) {
  if (p.levels <= 1) return static_cast<std::size_t>(p.fine_points);
  const double f = double(level) / (p.levels - 1);
  return static_cast<std::size_t>(p.coarse_points * std::pow(double(p.fine_points) / p.coarse_points, f));
}

std::vector<Term> make_terms(const PreopBoundarySamples& preop, const IntraopDistanceMaps& intraop,
                             const AffineRegistrationParameters& p, int level,
                             const Eigen::Vector3d& centre, double radius) {
  std::vector<Term> terms;
  const std::size_t n_outer = std::min(preop.outer_mm.size(), level_points(p, level));
  const double fraction = double(n_outer) / std::max<std::size_t>(preop.outer_mm.size(), 1);
  auto add = [&](const std::vector<Eigen::Vector3d>& pts, std::size_t n, const ImageF& sdf, double w) {
    if (n == 0 || w <= 0 || sdf.voxels.empty()) return;
    Term term;
    term.sdf = &sdf;
    term.weight = w / double(n);
    term.q.reserve(n);
    for (std::size_t i = 0; i < n; ++i) term.q.push_back((pts[i] - centre) / radius);
    terms.push_back(std::move(term));
  };
  add(preop.outer_mm, n_outer, intraop.outer_sdf_mm, p.brain_weight);
  // Ventricle points: the same fraction, but enough of them to count at coarse levels.
  const std::size_t n_vent = std::min(
      preop.ventricle_mm.size(),
      std::max<std::size_t>(300, static_cast<std::size_t>(fraction * preop.ventricle_mm.size())));
  add(preop.ventricle_mm, n_vent, intraop.ventricle_sdf_mm, p.ventricle_weight);
  return terms;
}

// Eigenvectors sorted by decreasing eigenvalue; false when two eigenvalues are
// too close for the axes to be meaningful.
bool principal_axes(const Eigen::Matrix3d& cov, double min_ratio, Eigen::Matrix3d* axes) {
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);  // ascending
  const Eigen::Vector3d ev = es.eigenvalues();
  if (!(ev[0] > 0) || ev[1] / ev[0] < min_ratio || ev[2] / ev[1] < min_ratio) return false;
  *axes = es.eigenvectors().rowwise().reverse();
  return true;
}

// Rotation taking preop principal axes to intraop ones, with the sign choice
// (axes are defined up to sign) closest to the identity: scanners share the
// RAS convention, so heads are never upside down or reversed.
Eigen::Matrix3d principal_axes_rotation(const Eigen::Matrix3d& preop_axes,
                                        const Eigen::Matrix3d& intraop_axes) {
  Eigen::Matrix3d best = Eigen::Matrix3d::Identity();
  double best_trace = -std::numeric_limits<double>::infinity();
  for (int signs = 0; signs < 8; ++signs) {
    Eigen::Vector3d d;
    for (int a = 0; a < 3; ++a) d[a] = (signs >> a & 1) ? -1.0 : 1.0;
    const Eigen::Matrix3d R = intraop_axes * d.asDiagonal() * preop_axes.transpose();
    if (R.determinant() < 0) continue;
    if (R.trace() > best_trace) best_trace = R.trace(), best = R;
  }
  return best;
}

std::vector<AffineState> initial_candidates(const PreopBoundarySamples& preop,
                                            const IntraopDistanceMaps& intraop,
                                            const AffineRegistrationParameters& p, double radius) {
  const MaskMoments& mp = preop.outer_moments;
  const MaskMoments& mi = intraop.outer_moments;
  const double volume_scale = std::cbrt(mi.volume_ml / mp.volume_ml);
  std::vector<Eigen::Matrix3d> rotations{Eigen::Matrix3d::Identity()};
  Eigen::Matrix3d ap, ai;
  if (principal_axes(mp.covariance_mm2, p.principal_axes_min_eigen_ratio, &ap) &&
      principal_axes(mi.covariance_mm2, p.principal_axes_min_eigen_ratio, &ai)) {
    rotations.push_back(principal_axes_rotation(ap, ai));
  }
  // Unit scale as well: a field of view that crops the brain shrinks the
  // intraop volume, and the volume ratio would then be wrong.
  std::vector<double> scales{volume_scale};
  if (std::abs(volume_scale - 1.0) > 0.02) scales.push_back(1.0);
  std::vector<AffineState> out;
  for (const auto& R : rotations)
    for (double s : scales) out.push_back({s * radius * R, mi.centroid_mm});
  return out;
}


// A start the coarse level does not already reach from a candidate: more
// than half the pose sweep's step (15 degrees) from every one of them. Nearer
// starts would only repeat the search they make (and their noise decide
// between near-equal answers).
void add_if_another_pose(const AffineState& start, std::vector<AffineState>& candidates) {
  for (const AffineState& existing : candidates)
    if (rotation_between_deg(existing.B, start.B) <= 15.0) return;
  candidates.push_back(start);
}

// The robust cost alone (evaluate's, without the normal equations that cost
// four fifths of its time): what the pose sweep compares.
double cost_only(const std::vector<Term>& terms, const AffineState& s, double c) {
  double cost = 0;
  for (const Term& term : terms) {
    const LinearSampler sampler(*term.sdf);
    for (const Eigen::Vector3d& q : term.q) {
      double r;
      cost += term.weight * (sampler.sample(s.B * q + s.t, &r, nullptr) ? gm_rho(r, c) : 0.5 * c * c);
    }
  }
  return cost;
}

// The head's pose swept where the candidates above cannot reach: a head
// turned in its clamp for a lateral approach (60-90 degrees about S-I), or
// flexed, which the scanner's RAS does not follow. The coarse level's cost
// at every 30 degrees of yaw about the preop's S-I axis, with pitch and roll
// 0 and +-30 (108 poses: any pose within 15 degrees of yaw, and of pitch and
// roll up to 45, of one), the centroids on each other and the volume's
// scale; the cheapest pose is one more candidate when it is another pose
// (add_if_another_pose). 108 costs of the coarse level's points, without
// the normal equations: 9 ms measured on a loaded machine (24 ms with them).
void add_swept_pose(const std::vector<Term>& coarse_terms, double c, const PreopBoundarySamples& preop,
                    const IntraopDistanceMaps& intraop, double radius, std::vector<AffineState>& candidates) {
  constexpr double kStepDeg = 30.0;
  const double scale = std::cbrt(intraop.outer_moments.volume_ml / preop.outer_moments.volume_ml);
  std::vector<AffineState> poses;
  for (const SweptPose& pose : swept_poses(kStepDeg, kStepDeg))
    poses.push_back({scale * radius * swept_pose_rotation(pose), intraop.outer_moments.centroid_mm});
  // Each pose's cost on its own, the two halves side by side; the cheapest
  // taken in pose order: the same on one core or two.
  std::vector<double> cost(poses.size());
  parallel_halves(poses.size(), 1, [&](std::size_t begin, std::size_t end) {
    for (std::size_t i = begin; i < end; ++i) cost[i] = cost_only(coarse_terms, poses[i], c);
  });
  const auto cheapest = std::min_element(cost.begin(), cost.end()) - cost.begin();
  const AffineState& best = poses[static_cast<std::size_t>(cheapest)];
  add_if_another_pose(best, candidates);
}

Eigen::Matrix4d to_matrix(const AffineState& s, const Eigen::Vector3d& centre, double radius) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d A = s.B / radius;
  m.topLeftCorner<3, 3>() = A;
  m.topRightCorner<3, 1>() = s.t - A * centre;
  return m;
}

// The full affine from the finest similarity, and the result's report.
// initial_state: where the search started (its cost is reported).
AffineRegistrationResult finish_affine(const std::vector<Term>& fine_terms, const AffineRegistrationParameters& p,
                                       const Eigen::Vector3d& centre, double radius, LevelOutcome best,
                                       int iterations, const AffineState& initial_state) {
  AffineRegistrationResult result;
  // Then the full affine from the similarity, at the finest level, with the
  // robust scale the data give: c = data_scale_factor x the MAD sigma of the
  // residuals (segmentation noise), between min_robust_scale_mm and
  // robust_scale_mm. Points beyond ~2c (the sunken or dented part) then
  // weigh < 4 % and cannot shear the fit toward them.
  const double sigma_mm = mad_sigma_mm(fine_terms, best.state);
  const double fit_c = std::clamp(p.data_scale_factor * sigma_mm, p.min_robust_scale_mm, p.robust_scale_mm);
  // The affine's five extra parameters (anisotropic scale, shear) may be
  // kept only when they explain a misfit of the whole outline
  // (max_affine_sigma_ratio < 1): then the median residual falls (a real 2 %
  // anisotropy: MAD sigma 0.96 -> 0.42 mm), while a local sink's flanks
  // barely move it (25 mm sink: 0.56 -> 0.51 mm). Off by default
  // (docs/DESIGN.md, "Quality gates").
  double affine_sigma_mm = sigma_mm;
  if (p.affine_stage) {
    LevelOutcome affine = run_level(fine_terms, best.state, fit_c, Model::affine, p.iterations_per_level, p.tolerance_mm);
    iterations += affine.iterations;
    affine_sigma_mm = mad_sigma_mm(fine_terms, affine.state);
    result.affine_kept = affine_sigma_mm <= p.max_affine_sigma_ratio * sigma_mm;
    if (result.affine_kept) best = std::move(affine);
  }
  const bool tolerance_met = best.converged;

  const Evaluation initial = evaluate(fine_terms, initial_state, p.robust_scale_mm);
  const Evaluation final_eval = evaluate(fine_terms, best.state, p.robust_scale_mm);
  result.intraop_from_preop = to_matrix(best.state, centre, radius);
  result.iterations = iterations;
  result.initial_cost = initial.cost;
  result.final_cost = final_eval.cost;
  result.points_used = final_eval.valid;
  result.robust_scale_mm = fit_c;
  result.residual_sigma_mm = sigma_mm;
  result.tolerance_met = tolerance_met;
  if (final_eval.valid > 0) {
    result.rms_surface_distance_mm = std::sqrt(final_eval.sum_squares / double(final_eval.valid));
    result.inlier_fraction = double(final_eval.inliers) / double(final_eval.valid);
  }
  const double det = result.intraop_from_preop.topLeftCorner<3, 3>().determinant();
  const double in_view = double(final_eval.valid) / std::max<std::size_t>(final_eval.total, 1);

  // Converged means a result one may use: a plausible matrix that fits the
  // data. Whether the last LM step was still above tolerance_mm when the
  // iteration cap or a stall stopped it does not matter at a good fit (the
  // cost is flat there); it is reported, not refused.
  std::ostringstream msg;
  msg.precision(3);
  const bool plausible = det > 0.5 && det < 2.0 && result.intraop_from_preop.allFinite();
  const bool good_fit = result.inlier_fraction >= p.min_inlier_fraction && in_view >= 0.3;
  result.plausible = plausible;
  result.converged = plausible && good_fit;
  if (result.converged) {
    msg << (tolerance_met ? "converged" : "converged (good fit; last step above tolerance)");
  } else if (!plausible) {
    msg << "failed: implausible affine (determinant " << det << ")";
  } else {
    msg << "poor fit: " << 100 * result.inlier_fraction << "% of surface points within "
        << 2 * p.robust_scale_mm << " mm, " << 100 * in_view << "% inside the intraop image";
  }
  msg << " after " << iterations << " iterations; rms surface distance "
      << result.rms_surface_distance_mm << " mm over " << result.points_used << " points; residual sigma "
      << sigma_mm << " mm (" << affine_sigma_mm << " with the full affine, "
      << (result.affine_kept ? "kept" : "not kept: the similarity is the result") << "), robust scale " << fit_c << " mm";
  result.message = msg.str();
  return result;
}

}  // namespace

AffineRegistrationResult register_affine(const PreopBoundarySamples& preop,
                                         const IntraopDistanceMaps& intraop,
                                         const AffineRegistrationParameters& p,
                                         const Eigen::Matrix4d* start, const Eigen::Matrix4d* candidate) {
  if (p.levels < 1 || p.coarse_points < 12 || p.fine_points < 12 || !(p.robust_scale_mm > 0) ||
      p.iterations_per_level < 1 || !(p.min_robust_scale_mm > 0) || p.min_robust_scale_mm > p.robust_scale_mm ||
      !(p.data_scale_factor > 0)) {
    throw InputError("affine registration: invalid parameters (levels, point counts, "
                     "iterations must be positive; 0 < min_robust_scale_mm <= robust_scale_mm; data_scale_factor > 0)");
  }
  if (preop.outer_mm.size() < 12 || intraop.outer_sdf_mm.voxels.empty() ||
      !(preop.outer_moments.volume_ml > 0) || !(intraop.outer_moments.volume_ml > 0)) {
    throw InputError("affine registration: empty brain outline in the preop or intraop label map");
  }
  const Eigen::Vector3d centre = preop.outer_moments.centroid_mm;
  const double radius = std::sqrt(preop.outer_moments.covariance_mm2.trace());
  if (start) {
    // A warm start is within a voxel or two: the coarse levels and the
    // candidate starts exist for capture range, which it does not need.
    AffineState from{start->topLeftCorner<3, 3>() * radius,
                     start->topRightCorner<3, 1>() + start->topLeftCorner<3, 3>() * centre};
    const auto fine_terms = make_terms(preop, intraop, p, p.levels - 1, centre, radius);
    LevelOutcome best = run_level(fine_terms, from, p.robust_scale_mm, Model::similarity, p.iterations_per_level,
                                  p.tolerance_mm);
    const int iterations = best.iterations;
    return finish_affine(fine_terms, p, centre, radius, std::move(best), iterations, from);
  }

  // Similarity, coarse to fine: the coarse level from every candidate start
  // (lowest cost wins), then more points and a tighter robust scale.
  const auto level_c = [&](int level) {
    return p.robust_scale_mm * std::pow(p.coarse_scale_factor, p.levels - 1 - level);
  };
  const auto level_tolerance = [&](int level) {
    return level == p.levels - 1 ? p.tolerance_mm : p.coarse_tolerance_mm;
  };
  const std::vector<Term> coarse_terms = make_terms(preop, intraop, p, 0, centre, radius);
  auto candidates = initial_candidates(preop, intraop, p, radius);
  if (candidate)
    add_if_another_pose({candidate->topLeftCorner<3, 3>() * radius,
                         candidate->topRightCorner<3, 1>() + candidate->topLeftCorner<3, 3>() * centre},
                        candidates);
  add_swept_pose(coarse_terms, level_c(0), preop, intraop, radius, candidates);
  LevelOutcome best;
  double best_cost = std::numeric_limits<double>::infinity();
  for (const AffineState& candidate : candidates) {
    LevelOutcome o = run_level(coarse_terms, candidate, level_c(0), Model::similarity, p.iterations_per_level,
                               level_tolerance(0));
    if (o.eval.cost < best_cost) best_cost = o.eval.cost, best = std::move(o);
  }
  int iterations = best.iterations;
  for (int level = 1; level < p.levels; ++level) {
    best = run_level(make_terms(preop, intraop, p, level, centre, radius), best.state, level_c(level),
                     Model::similarity, p.iterations_per_level, level_tolerance(level));
    iterations += best.iterations;
  }
  return finish_affine(make_terms(preop, intraop, p, p.levels - 1, centre, radius), p, centre, radius,
                       std::move(best), iterations, candidates.front());
}

AffineRegistrationResult register_affine(const LabelImage& preop_labels,
                                         const LabelImage& intraop_labels,
                                         const AffineRegistrationParameters& params,
                                         std::uint16_t brain_label, std::uint16_t ventricle_label) {
  const PreopBoundarySamples preop = prepare_preop_samples(preop_labels, brain_label, ventricle_label);
  const IntraopDistanceMaps intraop = prepare_intraop_maps(intraop_labels, brain_label, ventricle_label);
  return register_affine(preop, intraop, params);
}

AffineRegistrationParameters placement_affine(const AffineRegistrationParameters& full) {
  AffineRegistrationParameters light = full;
  light.fine_points = std::max(light.coarse_points, light.fine_points / 4);
  light.levels = std::min(light.levels, 2);
  return light;
}

}  // namespace brainshift
