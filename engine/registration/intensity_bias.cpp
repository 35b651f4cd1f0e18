#include "registration/intensity_bias.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <utility>
#include <sstream>

#include "registration/intensity_robust.h"

namespace brainshift::intensity {
namespace {

int basis_size(int degree) { return (degree + 1) * (degree + 2) * (degree + 3) / 6; }

// Monomials x^a y^b z^c with a + b + c <= degree (at most 3).
void bias_basis(const Eigen::Vector3f& q, int degree, double* out) {
  double px[4] = {1, q.x(), 0, 0}, py[4] = {1, q.y(), 0, 0}, pz[4] = {1, q.z(), 0, 0};
  for (int e = 2; e <= 3; ++e) px[e] = px[e - 1] * px[1], py[e] = py[e - 1] * py[1], pz[e] = pz[e - 1] * pz[1];
  int n = 0;
  for (int total = 0; total <= degree; ++total)
    for (int a = total; a >= 0; --a)
      for (int b = total - a; b >= 0; --b) out[n++] = px[a] * py[b] * pz[total - a - b];
}


// Weighted least squares of I ~ b(x) P + d (linear in b's coefficients and
// d; d = 0 without an offset). False when the system is singular or b is not
// clearly positive on the samples.
bool solve_bias(const std::vector<Sample>& s, const std::vector<double>& preop, const std::vector<double>& w,
                int degree, bool with_offset, BiasModel* out) {
  const int k = basis_size(degree), m1 = with_offset ? k + 1 : k;
  Eigen::MatrixXd normal = Eigen::MatrixXd::Zero(m1, m1);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(m1);
  double row[21];
  for (std::size_t n = 0; n < s.size(); ++n) {
    if (w[n] <= 0) continue;
    bias_basis(s[n].poly, degree, row);
    for (int a = 0; a < k; ++a) row[a] *= preop[n];
    if (with_offset) row[k] = 1.0;
    for (int a = 0; a < m1; ++a) {  // lower triangle, plain loops: sizes are tiny
      const double wa = w[n] * row[a];
      for (int b = 0; b <= a; ++b) normal(a, b) += wa * row[b];
      rhs[a] += wa * s[n].intensity;
    }
  }
  normal.triangularView<Eigen::StrictlyUpper>() = normal.transpose();
  Eigen::LDLT<Eigen::MatrixXd> ldlt(normal);
  if (ldlt.info() != Eigen::Success || ldlt.rcond() < 1e-12) return false;
  const Eigen::VectorXd x = ldlt.solve(rhs);
  BiasModel m;
  m.degree = degree;
  m.coef = x.head(k);
  m.offset = with_offset ? x[k] : 0.0;
  double b_min = std::numeric_limits<double>::infinity(), b_sum = 0;
  for (const auto& sample : s) {
    const double b = m.at(sample.poly);
    b_min = std::min(b_min, b);
    b_sum += b;
  }
  if (!(b_min > 0.2 * b_sum / static_cast<double>(s.size()))) return false;  // not a plausible coil bias
  *out = m;
  return true;
}

// Weighted partial R^2 of the fit: the share of the variance a smooth field
// of position alone (I ~ b0(x), b0 of the model's degree, least squares)
// leaves that the model explains, 1 - sum w r^2 / sum w r0^2. Against the
// plain variance an image of any head would score: its tissue classes have
// large-scale trends (white matter deep, grey matter outside) that the bias
// polynomial fits whatever the preop says.
double explained_variance(const std::vector<Sample>& s, const std::vector<double>& preop,
                          const std::vector<double>& w, const BiasModel& m) {
  double sw = 0, swi = 0;
  for (std::size_t n = 0; n < s.size(); ++n) sw += w[n], swi += w[n] * s[n].intensity;
  if (!(sw > 0)) return 0;
  const double mean = swi / sw;
  BiasModel trend;
  const bool has_trend = solve_bias(s, std::vector<double>(s.size(), 1.0), w, m.degree, false, &trend);
  double residual = 0, total = 0;
  for (std::size_t n = 0; n < s.size(); ++n) {
    const double r = s[n].intensity - (m.at(s[n].poly) * preop[n] + m.offset);
    const double r0 = s[n].intensity - (has_trend ? trend.at(s[n].poly) : mean);
    residual += w[n] * r * r;
    total += w[n] * r0 * r0;
  }
  return total > 0 ? 1.0 - residual / total : 0.0;
}

// One robust (reweighted) fit of a given form; false when it fails.
bool robust_fit(const std::vector<Sample>& s, const std::vector<double>& p, const std::vector<double>& w, int degree,
                bool with_offset, double robust_scale, BiasModel* m) {
  std::vector<double> wn = w;
  bool ok = solve_bias(s, p, wn, degree, with_offset, m);
  for (int round = 0; ok && round < 2; ++round) {
    std::vector<double> r(s.size());
    std::vector<double> abs_r;
    for (std::size_t n = 0; n < s.size(); ++n) {
      r[n] = s[n].intensity - (m->at(s[n].poly) * p[n] + m->offset);
      if (w[n] > 0) abs_r.push_back(std::abs(r[n]));
    }
    const double scale = std::max(robust_scale * robust_sigma(abs_r), 1e-12);
    for (std::size_t n = 0; n < s.size(); ++n) wn[n] = w[n] * geman_mcclure_weight(r[n], scale);
    ok = solve_bias(s, p, wn, degree, with_offset, m);
  }
  return ok;
}

// Preop intensity at each sample's current preop point and its weight (0
// where the point leaves the preop image).
void sample_preop(const std::vector<Sample>& s, const Lattice& lattice, const LinearSampler& preop,
                  std::vector<double>* p, std::vector<double>* w) {
  p->assign(s.size(), 0.0);
  w->assign(s.size(), 0.0);
  for (std::size_t n = 0; n < s.size(); ++n) {
    double value;
    if (preop.sample(s[n].preop_mm(lattice.value(s[n].cell)), &value, nullptr)) (*p)[n] = value, (*w)[n] = s[n].weight;
  }
}

// f from the joint histogram: the median of I / b per preop bin between the
// 1st and 99th percentiles of P (the tails are a few partial-volume voxels),
// bins of at least ~250 samples each (8-32 bins: finer than the tissue
// classes' separation, coarse enough that a bin's median is stable to ~1/16
// of the noise), empty bins bridged linearly, one [1 2 1] smoothing pass.
// nullopt when P has no spread or fewer than 3 bins are populated.
std::optional<Transfer> bin_transfer(const std::vector<Sample>& s, const std::vector<double>& p,
                                     const std::vector<double>& w, const std::vector<double>& b) {
  std::vector<double> used;
  for (std::size_t n = 0; n < s.size(); ++n)
    if (w[n] > 0) used.push_back(p[n]);
  if (used.size() < 500) return std::nullopt;
  const auto quantile = [&](double q) {
    const auto at = used.begin() + static_cast<std::ptrdiff_t>(q * static_cast<double>(used.size() - 1));
    std::nth_element(used.begin(), at, used.end());
    return *at;
  };
  const double lo = quantile(0.01), hi = quantile(0.99);
  if (!(hi > lo)) return std::nullopt;
  const int bins = static_cast<int>(std::clamp<std::size_t>(used.size() / 250, 8, 32));
  Transfer t;
  t.identity = false;
  t.step = (hi - lo) / bins;
  t.first_centre = lo + 0.5 * t.step;
  std::vector<std::vector<double>> members(bins);
  for (std::size_t n = 0; n < s.size(); ++n) {
    if (w[n] <= 0 || !(b[n] > 0)) continue;
    const int k = std::clamp(static_cast<int>(std::floor((p[n] - lo) / t.step)), 0, bins - 1);
    members[k].push_back(s[n].intensity / b[n]);
  }
  std::vector<int> filled;
  std::vector<double> value(bins, 0.0);
  for (int k = 0; k < bins; ++k)
    if (members[k].size() >= 10) value[k] = median(std::move(members[k])), filled.push_back(k);
  if (filled.size() < 3) return std::nullopt;
  for (int k = 0; k < bins; ++k) {  // bridge the empty bins; constant beyond the outer filled ones
    const auto next = std::lower_bound(filled.begin(), filled.end(), k);
    if (next != filled.end() && *next == k) continue;
    if (next == filled.begin()) value[k] = value[filled.front()];
    else if (next == filled.end()) value[k] = value[filled.back()];
    else {
      const int a = *(next - 1), c = *next;
      value[k] = value[a] + (value[c] - value[a]) * (k - a) / static_cast<double>(c - a);
    }
  }
  t.value.resize(bins);
  for (int k = 0; k < bins; ++k)
    t.value[k] = 0.25 * (value[std::max(k - 1, 0)] + 2 * value[k] + value[std::min(k + 1, bins - 1)]);
  t.slope.resize(bins);
  for (int k = 0; k < bins; ++k) {
    const int a = std::max(k - 1, 0), c = std::min(k + 1, bins - 1);
    t.slope[k] = (t.value[c] - t.value[a]) / ((c - a) * t.step);
  }
  return t;
}

}  // namespace

double Transfer::at(double p, double* derivative) const {
  if (identity) {
    if (derivative) *derivative = 1.0;
    return p;
  }
  const double x = (p - first_centre) / step;
  const int last = static_cast<int>(value.size()) - 1;
  if (!(x > 0) || x >= last) {
    if (derivative) *derivative = 0.0;
    return x >= last ? value.back() : value.front();
  }
  const int k = static_cast<int>(x);
  const double u = x - k, u2 = u * u, u3 = u2 * u;
  const double v0 = value[k], v1 = value[k + 1], m0 = step * slope[k], m1 = step * slope[k + 1];
  if (derivative)
    *derivative = ((6 * u2 - 6 * u) * v0 + (3 * u2 - 4 * u + 1) * m0 + (6 * u - 6 * u2) * v1 + (3 * u2 - 2 * u) * m1) / step;
  return (2 * u3 - 3 * u2 + 1) * v0 + (u3 - 2 * u2 + u) * m0 + (3 * u2 - 2 * u3) * v1 + (u3 - u2) * m1;
}

double BiasModel::at(const Eigen::Vector3f& q) const {
  double basis[20];
  bias_basis(q, degree, basis);
  double b = 0;
  for (int n = 0; n < coef.size(); ++n) b += coef[n] * basis[n];
  return b;
}

std::optional<BiasModel> fit_bias(const std::vector<Sample>& s, const Lattice& lattice, const LinearSampler& preop,
                                  int degree, double robust_scale) {
  std::vector<double> p, w;
  sample_preop(s, lattice, preop, &p, &w);
  BiasModel m;
  bool ok = false;
  for (int d = degree; d >= 0 && !ok; --d) ok = robust_fit(s, p, w, d, true, robust_scale, &m);
  if (!ok) ok = robust_fit(s, p, w, 0, false, robust_scale, &m);
  if (!ok) return std::nullopt;
  m.explained = explained_variance(s, p, w, m);
  return m;
}

std::optional<BiasModel> fit_transfer_model(const std::vector<Sample>& s, const Lattice& lattice,
                                            const LinearSampler& preop, int degree, double robust_scale) {
  std::vector<double> p, w;
  sample_preop(s, lattice, preop, &p, &w);
  std::vector<double> b(s.size(), 1.0), f(s.size());
  std::optional<BiasModel> model;
  // f and b alternate: f from I / b, then b from I ~ b f. Three rounds: the
  // bias is smooth and f's bins average over the whole brain, so the second
  // round changes b by a fraction of its first-round change.
  for (int round = 0; round < 3; ++round) {
    std::optional<Transfer> t = bin_transfer(s, p, w, b);
    if (!t) return std::nullopt;
    for (std::size_t n = 0; n < s.size(); ++n) f[n] = t->at(p[n], nullptr);
    BiasModel m;
    bool ok = false;
    for (int d = degree; d >= 0 && !ok; --d) ok = robust_fit(s, f, w, d, false, robust_scale, &m);
    if (!ok) return std::nullopt;
    double mean_b = 0;  // b and f share a scale: b's mean is 1, f carries the level
    for (const Sample& x : s) mean_b += m.at(x.poly);
    mean_b /= static_cast<double>(s.size());
    m.coef /= mean_b;
    for (double& v : t->value) v *= mean_b;
    for (double& v : t->slope) v *= mean_b;
    m.transfer = std::move(*t);
    for (std::size_t n = 0; n < s.size(); ++n) b[n] = m.at(s[n].poly);
    model = std::move(m);
  }
  for (std::size_t n = 0; n < s.size(); ++n) f[n] = model->transfer.at(p[n], nullptr);
  model->explained = explained_variance(s, f, w, *model);
  return model;
}

std::optional<BiasModel> fit_intensity_model(const std::vector<Sample>& s, const Lattice& lattice,
                                             const LinearSampler& preop, int degree, double robust_scale,
                                             double min_explained) {
  std::optional<BiasModel> linear = fit_bias(s, lattice, preop, degree, robust_scale);
  std::optional<BiasModel> curved = fit_transfer_model(s, lattice, preop, degree, robust_scale);
  if (!curved) return linear;
  if (!linear || linear->explained < min_explained) return curved;
  return 1.0 - curved->explained < 0.5 * (1.0 - linear->explained) ? curved : linear;
}

std::string describe(const BiasModel& m) {
  std::ostringstream o;
  if (m.transfer.identity)
    o << "I = b(x) P + d, b polynomial of degree " << m.degree << " (" << m.coef.size() << " terms), d " << m.offset;
  else
    o << "I = b(x) f(P), f transfer function of " << m.transfer.value.size() << " bins over P in ["
      << m.transfer.first_centre - 0.5 * m.transfer.step << ", "
      << m.transfer.first_centre + (static_cast<double>(m.transfer.value.size()) - 0.5) * m.transfer.step
      << "], b polynomial of degree " << m.degree << " (" << m.coef.size() << " terms)";
  return o.str();
}

void update_bias(std::vector<Sample>& samples, const BiasModel& m) {
  for (Sample& s : samples) s.bias = static_cast<float>(m.at(s.poly));
}

std::string untrusted_image(const std::optional<BiasModel>& bias, double min_explained) {
  if (!bias) return "the intraop intensities do not follow the preop T1 (no positive bias fits, with or without a transfer function)";
  if (bias->explained < min_explained) {
    std::ostringstream o;
    o << std::fixed << std::setprecision(2) << "the intensity model explains only " << bias->explained
      << " of the intraop intensity variance (minimum " << min_explained << ")";
    return o.str();
  }
  return "";
}

}  // namespace brainshift::intensity
