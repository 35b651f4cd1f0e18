#include "registration/intensity_bias.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
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

// Weighted R^2 of the fit: 1 - sum w r^2 / sum w (I - mean I)^2.
double explained_variance(const std::vector<Sample>& s, const std::vector<double>& preop,
                          const std::vector<double>& w, const BiasModel& m) {
  double sw = 0, swi = 0;
  for (std::size_t n = 0; n < s.size(); ++n) sw += w[n], swi += w[n] * s[n].intensity;
  if (!(sw > 0)) return 0;
  const double mean = swi / sw;
  double residual = 0, total = 0;
  for (std::size_t n = 0; n < s.size(); ++n) {
    const double r = s[n].intensity - (m.at(s[n].poly) * preop[n] + m.offset);
    residual += w[n] * r * r;
    total += w[n] * (s[n].intensity - mean) * (s[n].intensity - mean);
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

}  // namespace

double BiasModel::at(const Eigen::Vector3f& q) const {
  double basis[20];
  bias_basis(q, degree, basis);
  double b = 0;
  for (int n = 0; n < coef.size(); ++n) b += coef[n] * basis[n];
  return b;
}

std::optional<BiasModel> fit_bias(const std::vector<Sample>& s, const Lattice& lattice, const LinearSampler& preop,
                                  int degree, double robust_scale) {
  std::vector<double> p(s.size(), 0.0), w(s.size(), 0.0);
  for (std::size_t n = 0; n < s.size(); ++n) {
    double value;
    if (preop.sample(s[n].preop_mm(lattice.value(s[n].cell)), &value, nullptr)) p[n] = value, w[n] = s[n].weight;
  }
  BiasModel m;
  bool ok = false;
  for (int d = degree; d >= 0 && !ok; --d) ok = robust_fit(s, p, w, d, true, robust_scale, &m);
  if (!ok) ok = robust_fit(s, p, w, 0, false, robust_scale, &m);
  if (!ok) return std::nullopt;
  m.explained = explained_variance(s, p, w, m);
  return m;
}

std::string describe(const BiasModel& m) {
  std::ostringstream o;
  o << "I = b(x) P + d, b polynomial of degree " << m.degree << " (" << m.coef.size() << " terms), d "
    << m.offset;
  return o.str();
}

void update_bias(std::vector<Sample>& samples, const BiasModel& m) {
  for (Sample& s : samples) s.bias = static_cast<float>(m.at(s.poly));
}

std::string untrusted_image(const std::optional<BiasModel>& bias, double min_explained) {
  if (!bias) return "the intraop intensities do not follow the preop T1 (no positive bias fits)";
  if (bias->explained < min_explained) {
    std::ostringstream o;
    o << std::fixed << std::setprecision(2) << "the bias model explains only " << bias->explained
      << " of the intraop intensity variance (minimum " << min_explained << ")";
    return o.str();
  }
  return "";
}

}  // namespace brainshift::intensity
