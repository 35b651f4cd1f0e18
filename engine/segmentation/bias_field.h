#pragma once
// A smooth multiplicative intensity bias (receive-coil sensitivity, B1
// inhomogeneity) as a low-order polynomial in the log domain:
//   image(x) = b(x) * tissue(x),   log b(x) = sum_j c_j phi_j(x)
// phi_j: the monomials x^a y^b z^c (a + b + c <= degree) of voxel coordinates
// scaled to [-1, 1] over the grid. A polynomial of degree 2-3 spans the few
// coil-scale oscillations a head coil or a surface coil puts over a brain
// (wavelength of tens of cm at 1.5 T and below) and cannot follow anatomy.
#include <Eigen/Dense>
#include <array>
#include <cstddef>
#include <vector>

#include "core/image.h"

namespace brainshift::segmentation {

class LogBiasField {
 public:
  LogBiasField(const Grid3& grid, int degree);
  int degree() const { return degree_; }
  std::size_t terms() const { return powers_.size(); }
  // log b at voxel (i, j, k).
  double log_bias(int i, int j, int k) const;
  // log b on every voxel of the grid (grid order).
  std::vector<float> log_bias_image() const;
  // log b on a box of voxels given in this field's voxel indices (origin may
  // be negative, the box may reach past the grid: the polynomial extends
  // smoothly), box order. A later round that classifies another box of the
  // same image reuses the fitted field there.
  std::vector<float> log_bias_box(const std::array<int, 3>& origin, const std::array<int, 3>& dims) const;
  // Weighted least squares of the coefficients on (voxel, log-ratio, weight)
  // samples; the weighted mean of log b over `weights` is then removed, so the
  // bias does not trade its level for the tissue means. False (coefficients
  // unchanged) when the samples cannot determine the polynomial.
  bool fit(const std::vector<std::array<int, 3>>& voxels, const std::vector<double>& log_ratio,
           const std::vector<double>& weights);
  const Eigen::VectorXd& coefficients() const { return coef_; }
  // Takes the coefficients of a field of lower degree on the same grid (the
  // monomials they share), zero for the others.
  void start_from(const LogBiasField& lower);

 private:
  double scaled(int axis, int index) const;
  Grid3 grid_;
  int degree_;
  std::vector<std::array<int, 3>> powers_;
  Eigen::VectorXd coef_;
};

}  // namespace brainshift::segmentation
