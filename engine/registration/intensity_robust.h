#pragma once
// Robust statistics shared by the intensity refinement's bias fit and its
// Gauss-Newton data term. Internal to the refinement.
#include <algorithm>
#include <cstddef>
#include <utility>
#include <vector>

namespace brainshift::intensity {

inline double geman_mcclure_weight(double r, double scale) {
  const double t = r / scale;
  const double d = 1.0 + t * t;
  return 1.0 / (d * d);
}

inline double median(std::vector<double> values) {
  if (values.empty()) return 0;
  const auto mid = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
  std::nth_element(values.begin(), mid, values.end());
  return *mid;
}

// 1.4826 * median |r|: the spread of Gaussian noise, unmoved by outliers.
inline double robust_sigma(std::vector<double> abs_residuals) { return 1.4826 * median(std::move(abs_residuals)); }

}  // namespace brainshift::intensity
