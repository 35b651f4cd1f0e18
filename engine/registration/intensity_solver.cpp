#include "registration/intensity_solver.h"

#include <algorithm>
#include <cmath>
#include <optional>
#include <utility>

#include "core/parallel.h"
#include "registration/intensity_bias.h"
#include "registration/intensity_robust.h"

namespace brainshift::intensity {
namespace {

// Data term's gradient and lumped Hessian per node. Lumping (phi phi^T ->
// diag(phi), valid as the trilinear weights are >= 0 and sum to 1) gives a
// matrix above the true Gauss-Newton one, so a step never overshoots the
// linearised model; the gradient is exact, so the fixed point is the same.
struct NodeSystem {
  using Sym3 = Eigen::Matrix<double, 6, 1>;  // xx, xy, xz, yy, yz, zz
  std::vector<Sym3> hessian;
  std::vector<Vec3> gradient;
  double sum_r2 = 0;
  std::size_t used = 0;
  // Mean over the used samples of the data term's curvature along one axis,
  // w |d r / d v|^2 / (3 sigma^2) (1/mm^2): what one sample tells of the
  // motion, averaged over edge orientations.
  double mean_curvature_per_mm2() const {
    double trace = 0;
    for (const Sym3& h : hessian) trace += h[0] + h[3] + h[5];  // the trilinear weights sum to 1
    return used ? trace / (3.0 * static_cast<double>(used)) : 0.0;
  }
  explicit NodeSystem(std::size_t n) : hessian(n, Sym3::Zero()), gradient(n, Vec3::Zero()) {}
  void add(const NodeSystem& o) {
    for (std::size_t n = 0; n < hessian.size(); ++n) hessian[n] += o.hessian[n], gradient[n] += o.gradient[n];
    sum_r2 += o.sum_r2;
    used += o.used;
  }
  Mat3 hessian_at(std::size_t n) const {
    const Sym3& h = hessian[n];
    Mat3 m;
    m << h[0], h[1], h[2], h[1], h[3], h[4], h[2], h[4], h[5];
    return m;
  }
};

struct DataTerm {
  const std::vector<Sample>& samples;
  const Lattice& lattice;
  const LinearSampler& preop;
  double offset = 0;  // bias model's d
  double sigma = 1;   // robust residual spread
  double robust_scale = 3;
  Transfer transfer;  // f of the intensity model

  double residual(const Sample& s, double preop_value) const {
    return s.intensity - (s.bias * transfer.at(preop_value, nullptr) + offset);
  }

  Vec3 point(std::size_t n) const { return samples[n].preop_mm(lattice.value(samples[n].cell)); }

  // fn(n, preop point) for every step-th sample of [begin, end).
  template <class Fn>
  void for_samples(std::size_t begin, std::size_t end, std::size_t step, Fn&& fn) const {
    for (std::size_t n = begin; n < end; n += step) fn(n, point(n));
  }

  void accumulate(std::size_t begin, std::size_t end, NodeSystem* out) const {
    const double scale = robust_scale * sigma;
    // The sums per sample kept here and added once: the two halves'
    // systems lie next to each other, their scalars on shared cache lines.
    double sum_r2 = 0;
    std::size_t used = 0;
    for_samples(begin, end, 1, [&](std::size_t n, const Vec3& y) {
      const Sample& s = samples[n];
      double value;
      Vec3 g;
      if (!preop.sample(y, &value, &g)) return;
      double slope;
      const double r = s.intensity - (s.bias * transfer.at(value, &slope) + offset);
      sum_r2 += r * r;
      ++used;
      const double w = s.weight * geman_mcclure_weight(r, scale) / (sigma * sigma);
      const Vec3 dr = -static_cast<double>(s.bias) * slope * (s.jac.cast<double>().transpose() * g);  // d r / d v
      NodeSystem::Sym3 h;
      h << dr[0] * dr[0], dr[0] * dr[1], dr[0] * dr[2], dr[1] * dr[1], dr[1] * dr[2], dr[2] * dr[2];
      h *= w;
      const Vec3 grad = w * r * dr;
      lattice.for_corners(s.cell, [&](int node, double phi) {
        out->hessian[node] += phi * h;
        out->gradient[node] += phi * grad;
      });
    });
    out->sum_r2 += sum_r2;
    out->used += used;
  }

  NodeSystem evaluate() const {
    NodeSystem halves[2] = {NodeSystem(lattice.size()), NodeSystem(lattice.size())};
    on_two_halves(samples.size(), [&](std::size_t b, std::size_t e, std::size_t half) { accumulate(b, e, &halves[half]); });
    halves[0].add(halves[1]);
    return std::move(halves[0]);
  }

  // Robust spread and RMS of the residuals on every 4th sample: enough for a
  // median and a report, at a quarter of a pass.
  std::pair<double, double> residual_spread_and_rms() const {
    std::vector<double> abs_r;
    abs_r.reserve(samples.size() / 4 + 1);
    double sum2 = 0;
    for_samples(0, samples.size(), 4, [&](std::size_t n, const Vec3& y) {
      double value;
      if (!preop.sample(y, &value, nullptr)) return;
      abs_r.push_back(std::abs(residual(samples[n], value)));
      sum2 += abs_r.back() * abs_r.back();
    });
    const double rms = abs_r.empty() ? 0.0 : std::sqrt(sum2 / static_cast<double>(abs_r.size()));
    return {robust_sigma(std::move(abs_r)), rms};
  }
};

// Membrane (graph Laplacian on the lattice's 6-neighbours) times alpha plus
// beta times the identity: the regulariser's Hessian.
void apply_prior(const Lattice& l, double alpha, double beta, const std::vector<Vec3>& x, std::vector<Vec3>* out) {
  out->resize(x.size());
  for (std::size_t n = 0; n < x.size(); ++n) (*out)[n] = beta * x[n];
  const int stride[3] = {1, l.dim(0), l.dim(0) * l.dim(1)};
  // Each edge once, along each axis: both ends get alpha (x_a - x_b).
  for (int axis = 0; axis < 3; ++axis)
    for (int c = 0; c < l.dim(2) - (axis == 2); ++c)
      for (int b = 0; b < l.dim(1) - (axis == 1); ++b)
        for (int a = 0; a < l.dim(0) - (axis == 0); ++a) {
          const int n = l.node(a, b, c), m = n + stride[axis];
          const Vec3 d = alpha * (x[n] - x[m]);
          (*out)[n] += d;
          (*out)[m] -= d;
        }
}

double dot(const std::vector<Vec3>& a, const std::vector<Vec3>& b) {
  double s = 0;
  for (std::size_t n = 0; n < a.size(); ++n) s += a[n].dot(b[n]);
  return s;
}

// (H + prior) step = -(gradient + prior * c), by conjugate gradients with the
// 3x3 node blocks as preconditioner. The lattice has a few thousand nodes:
// this costs far less than one pass over the samples.
std::vector<Vec3> gauss_newton_step(const NodeSystem& sys, const Lattice& l, double alpha, double beta) {
  const std::size_t n = l.size();
  std::vector<Vec3> prior_c, rhs(n), step(n, Vec3::Zero()), z(n), p, q;
  apply_prior(l, alpha, beta, l.coef_mm, &prior_c);
  for (std::size_t i = 0; i < n; ++i) rhs[i] = -(sys.gradient[i] + prior_c[i]);
  std::vector<Mat3> hessian(n), precond(n);
  for (std::size_t i = 0; i < n; ++i) {
    hessian[i] = sys.hessian_at(i);
    precond[i] = (hessian[i] + (6.0 * alpha + beta) * Mat3::Identity()).inverse();
  }
  auto apply = [&](const std::vector<Vec3>& x, std::vector<Vec3>* y) {
    apply_prior(l, alpha, beta, x, y);
    for (std::size_t i = 0; i < n; ++i) (*y)[i] += hessian[i] * x[i];
  };
  std::vector<Vec3> r = rhs;
  for (std::size_t i = 0; i < n; ++i) z[i] = precond[i] * r[i];
  p = z;
  double rz = dot(r, z);
  // A Gauss-Newton step only needs to be roughly right (the next one starts
  // from it): 1e-2 in the preconditioned residual norm, at most 6 rounds
  // (4, 6, 12 and 25 rounds give the same TRE on the phantom suite).
  const double stop = 1e-4 * std::max(rz, 1e-300);
  for (int it = 0; it < 6 && rz > stop; ++it) {
    apply(p, &q);
    const double pq = dot(p, q);
    if (!(pq > 0)) break;
    const double a = rz / pq;
    for (std::size_t i = 0; i < n; ++i) step[i] += a * p[i], r[i] -= a * q[i];
    for (std::size_t i = 0; i < n; ++i) z[i] = precond[i] * r[i];
    const double rz_next = dot(r, z);
    for (std::size_t i = 0; i < n; ++i) p[i] = z[i] + (rz_next / rz) * p[i];
    rz = rz_next;
  }
  return step;
}

// Applies the trust region and the bound on |v|; returns the largest move (mm).
double take_step(Lattice& l, const std::vector<Vec3>& step, const IntensityRefinementParameters& p) {
  double largest = 0;
  for (std::size_t i = 0; i < l.size(); ++i) {
    Vec3 d = step[i];
    if (d.norm() > p.max_step_mm) d *= p.max_step_mm / d.norm();
    Vec3 c = l.coef_mm[i] + d;
    if (c.norm() > p.max_correction_mm) c *= p.max_correction_mm / c.norm();
    largest = std::max(largest, (c - l.coef_mm[i]).norm());
    l.coef_mm[i] = c;
  }
  return largest;
}

// The regulariser's weights on the lattice (the Hessians of
// int |grad v|^2 dV and int |v|^2 dV, per sample density). With a smoothing
// length, relative to the data term's mean curvature at the start: the image
// then decides motion features longer than that length, and v fades to the
// FEM's answer over fem_trust_length_mm where the image is silent, whatever
// its noise, contrast and voxel size. The length is raised where the image
// says so little that its noise would move v by more than the position
// uncertainty of its own grid (voxel / sqrt(12)): a membrane of length l
// averages the data over about 8 pi l^3, so the noise's standard deviation
// in v is 1 / sqrt(8 pi l^3 density curvature). docs/DESIGN.md "Interior
// refinement from the intraop T1". Without a smoothing length, the fixed
// weights.
struct Prior {
  double alpha = 0, beta = 0;
  double length_mm = 0;  // the smoothing length in force (0: fixed weights)
};
Prior prior_weights(const IntensityRefinementParameters& p, double density_per_mm3, double h, double voxel_mm,
                    double curvature) {
  if (!(p.smoothing_length_mm > 0))
    return {p.membrane_weight * density_per_mm3 * h, p.shrink_weight_per_mm2 * density_per_mm3 * h * h * h, 0.0};
  const double info = std::max(density_per_mm3 * curvature, 1e-12);  // per mm^3 per mm^2 of motion
  const double tolerance2 = voxel_mm * voxel_mm / 12.0;
  const double noise_length = std::cbrt(1.0 / (8.0 * M_PI * info * tolerance2));
  const double l = std::min(std::max(p.smoothing_length_mm, noise_length), p.fem_trust_length_mm);
  const double t2 = p.fem_trust_length_mm * p.fem_trust_length_mm;
  const double membrane = l * l * curvature;  // the old weights' units (per sample)
  return {membrane * density_per_mm3 * h, membrane / t2 * density_per_mm3 * h * h * h, l};
}

}  // namespace

int optimise(Lattice& lattice, std::vector<Sample>& motion, const std::vector<Sample>& bias_samples,
             const LinearSampler& preop, const IntensityRefinementParameters& p, double density_per_mm3,
             double voxel_mm, double sigma_floor, IntensityRefinementReport* report) {
  const double h = lattice.spacing_mm();
  Prior prior;
  DataTerm data{motion, lattice, preop, 0.0, 1.0, p.robust_scale, Transfer{}};
  int it = 0;
  for (; it < p.iterations; ++it) {
    // The intensity model is fitted at v = 0 and re-fitted once half way,
    // when the edges are closer to aligned (the first fit stays if the second
    // fails); the kind chosen at the start (linear or with a transfer
    // function) is kept.
    if (it == 0 || it == p.iterations / 2) {
      const std::optional<BiasModel> bias =
          it == 0 ? fit_intensity_model(bias_samples, lattice, preop, p.bias_degree, p.robust_scale,
                                        p.min_explained_variance)
          : data.transfer.identity ? fit_bias(bias_samples, lattice, preop, p.bias_degree, p.robust_scale)
                                   : fit_transfer_model(bias_samples, lattice, preop, p.bias_degree, p.robust_scale);
      if (it == 0) {
        report->explained_variance = bias ? bias->explained : 0.0;
        report->skipped_reason = untrusted_image(bias, p.min_explained_variance);
        if (!report->skipped_reason.empty()) return 0;
      }
      if (bias) {
        update_bias(motion, *bias);
        data.offset = bias->offset;
        data.transfer = bias->transfer;
        report->bias_model = describe(*bias);
        report->explained_variance = bias->explained;
      }
      const auto [spread, rms] = data.residual_spread_and_rms();
      data.sigma = std::max(spread, sigma_floor);
      if (it == 0) report->rms_residual_before = rms;
    }
    const NodeSystem sys = data.evaluate();
    if (it == 0) {
      // Set once, at the start: as the edges align sigma falls and the image
      // is trusted more, as with fixed weights.
      report->data_curvature_per_mm2 = sys.mean_curvature_per_mm2();
      prior = prior_weights(p, density_per_mm3, h, voxel_mm, report->data_curvature_per_mm2);
      report->smoothing_length_mm = prior.length_mm;
    }
    const double moved = take_step(lattice, gauss_newton_step(sys, lattice, prior.alpha, prior.beta), p);
    if (moved < p.convergence_mm) {
      ++it;
      break;
    }
  }
  report->rms_residual_after = data.residual_spread_and_rms().second;
  return it;
}

}  // namespace brainshift::intensity
