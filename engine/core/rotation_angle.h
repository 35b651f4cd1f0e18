#pragma once
// How far apart two orientations are: the rotations of linear maps (an
// affine's 3 x 3 part, with scale and shear) by their polar decomposition
// L = R S, R the rotation nearest to L. Used where a search decides whether
// a pose is another pose or the same one refined (registration's pose
// sweeps, the image-only head placement's check).
#include <Eigen/Dense>

namespace brainshift {

inline Eigen::Matrix3d polar_rotation(const Eigen::Matrix3d& linear) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(linear, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d r = svd.matrixU() * svd.matrixV().transpose();
  if (r.determinant() < 0) r = -r;  // a mirror is no head's pose: its nearest rotation's negative
  return r;
}

// The angle of the rotation taking a's rotation to b's (degrees, 0-180).
inline double rotation_between_deg(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b) {
  return Eigen::AngleAxisd(polar_rotation(a).transpose() * polar_rotation(b)).angle() * 180.0 / 3.14159265358979323846;
}

}  // namespace brainshift
