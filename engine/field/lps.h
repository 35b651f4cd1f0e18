#pragma once
// The one place where RAS+ (NIfTI, this project) and LPS+ (ITK, DICOM, 3D Slicer
// transform files) meet. The two frames differ by a reflection of the first two
// axes: p_lps = F p_ras with F = diag(-1, -1, 1), and F is its own inverse.
// Points, origins and displacement vectors transform with F; a voxel-to-world
// matrix transforms as F * world_from_voxel (rows 0 and 1 negate).
// The OpenIGTLink link to 3D Slicer (server/igtl_encoder.h) converts nothing:
// Slicer's OpenIGTLinkIF takes IMAGE matrices and POLYDATA points as RAS.
#include <Eigen/Dense>

namespace brainshift {

inline Eigen::Matrix3d lps_from_ras_3x3() {
  return Eigen::Vector3d(-1.0, -1.0, 1.0).asDiagonal();
}

// Points and free vectors use the same sign flip (the frames share the origin).
inline Eigen::Vector3d ras_to_lps(const Eigen::Vector3d& ras) {
  return {-ras.x(), -ras.y(), ras.z()};
}
inline Eigen::Vector3d lps_to_ras(const Eigen::Vector3d& lps) {
  return {-lps.x(), -lps.y(), lps.z()};
}

// world_from_voxel expressed in the other frame: F * M (F = F^-1).
inline Eigen::Matrix4d lps_world_from_ras_world_matrix(const Eigen::Matrix4d& ras_world_from_voxel) {
  Eigen::Matrix4d flip = Eigen::Matrix4d::Identity();
  flip(0, 0) = -1.0;
  flip(1, 1) = -1.0;
  return flip * ras_world_from_voxel;
}
inline Eigen::Matrix4d ras_world_from_lps_world_matrix(const Eigen::Matrix4d& lps_world_from_voxel) {
  return lps_world_from_ras_world_matrix(lps_world_from_voxel);
}

}  // namespace brainshift
