#include "segmentation/bias_field.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"

namespace brainshift::segmentation {
namespace {
// A small non-negative integer power by multiplication: std::pow took a
// tenth of the EM's time, called per sample, term and axis in every iteration.
double power(double x, int e) {
  double r = 1;
  for (int n = 0; n < e; ++n) r *= x;
  return r;
}
}  // namespace

LogBiasField::LogBiasField(const Grid3& grid, int degree) : grid_(grid), degree_(degree) {
  if (degree < 0 || degree > 4) throw InputError("bias field degree must be in [0, 4]");
  for (int a = 0; a <= degree; ++a)
    for (int b = 0; a + b <= degree; ++b)
      for (int c = 0; a + b + c <= degree; ++c) powers_.push_back({a, b, c});
  coef_ = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(powers_.size()));
}

double LogBiasField::scaled(int axis, int index) const {
  const int n = grid_.dims[axis];
  return n > 1 ? 2.0 * index / (n - 1) - 1.0 : 0.0;
}

double LogBiasField::log_bias(int i, int j, int k) const {
  const double x = scaled(0, i), y = scaled(1, j), z = scaled(2, k);
  double s = 0;
  for (std::size_t t = 0; t < powers_.size(); ++t) {
    const auto& p = powers_[t];
    s += coef_[static_cast<Eigen::Index>(t)] * power(x, p[0]) * power(y, p[1]) * power(z, p[2]);
  }
  return s;
}

std::vector<float> LogBiasField::log_bias_image() const { return log_bias_box({0, 0, 0}, grid_.dims); }

std::vector<float> LogBiasField::log_bias_box(const std::array<int, 3>& origin, const std::array<int, 3>& n) const {
  // Separable: per-axis power tables, then the sum per voxel.
  std::array<std::vector<double>, 3> pw;
  for (int a = 0; a < 3; ++a) {
    pw[a].resize(static_cast<std::size_t>(std::max(n[a], 0)) * (degree_ + 1));
    for (int v = 0; v < n[a]; ++v) {
      double p = 1;
      for (int e = 0; e <= degree_; ++e, p *= scaled(a, origin[a] + v))
        pw[a][static_cast<std::size_t>(v) * (degree_ + 1) + e] = p;
    }
  }
  std::vector<float> out(static_cast<std::size_t>(std::max(n[0], 0)) * std::max(n[1], 0) * std::max(n[2], 0));
  const auto at = [&](int a, int v, int e) { return pw[a][static_cast<std::size_t>(v) * (degree_ + 1) + e]; };
  std::vector<double> yz(powers_.size());
  std::size_t index = 0;
  for (int k = 0; k < n[2]; ++k)
    for (int j = 0; j < n[1]; ++j) {
      for (std::size_t t = 0; t < powers_.size(); ++t)
        yz[t] = coef_[static_cast<Eigen::Index>(t)] * at(1, j, powers_[t][1]) * at(2, k, powers_[t][2]);
      for (int i = 0; i < n[0]; ++i) {
        double s = 0;
        for (std::size_t t = 0; t < powers_.size(); ++t) s += yz[t] * at(0, i, powers_[t][0]);
        out[index++] = static_cast<float>(s);
      }
    }
  return out;
}

void LogBiasField::start_from(const LogBiasField& lower) {
  coef_.setZero();
  for (std::size_t t = 0; t < powers_.size(); ++t)
    for (std::size_t u = 0; u < lower.powers_.size(); ++u)
      if (powers_[t] == lower.powers_[u]) coef_[static_cast<Eigen::Index>(t)] = lower.coef_[static_cast<Eigen::Index>(u)];
}

bool LogBiasField::fit(const std::vector<std::array<int, 3>>& voxels, const std::vector<double>& log_ratio,
                       const std::vector<double>& weights) {
  const auto m = static_cast<Eigen::Index>(powers_.size());
  Eigen::MatrixXd normal = Eigen::MatrixXd::Zero(m, m);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(m), mean_basis = Eigen::VectorXd::Zero(m);
  Eigen::VectorXd phi(m);
  double weight_sum = 0;
  for (std::size_t s = 0; s < voxels.size(); ++s) {
    const double w = weights[s];
    if (!(w > 0)) continue;
    const double x = scaled(0, voxels[s][0]), y = scaled(1, voxels[s][1]), z = scaled(2, voxels[s][2]);
    for (Eigen::Index t = 0; t < m; ++t) {
      const auto& p = powers_[static_cast<std::size_t>(t)];
      phi[t] = power(x, p[0]) * power(y, p[1]) * power(z, p[2]);
    }
    normal.selfadjointView<Eigen::Lower>().rankUpdate(phi, w);
    rhs += w * log_ratio[s] * phi;
    mean_basis += w * phi;
    weight_sum += w;
  }
  if (weight_sum <= 0) return false;
  normal = normal.selfadjointView<Eigen::Lower>();
  Eigen::LDLT<Eigen::MatrixXd> ldlt(normal);
  if (ldlt.info() != Eigen::Success || !ldlt.isPositive() ||
      ldlt.vectorD().minCoeff() <= 1e-10 * ldlt.vectorD().maxCoeff())
    return false;
  Eigen::VectorXd c = ldlt.solve(rhs);
  if (!c.allFinite()) return false;
  // powers_[0] is the constant: remove the weighted mean of log b.
  c[0] -= c.dot(mean_basis) / weight_sum;
  coef_ = c;
  return true;
}

}  // namespace brainshift::segmentation
