#pragma once
// Frames and the deformation produced by one registration. Shared by the
// registration, field, models and pipeline modules so that every stage speaks
// the same convention.
//
//   preop world   P: RAS+ mm of the preoperative image (atlas).
//   intraop world I: RAS+ mm of the intraoperative scan.
//
//   Forward map (preop -> intraop):  phi(p) = intraop_from_preop * p + w(p)
//     intraop_from_preop : the 12-parameter affine from the affine stage;
//     w                  : the non-rigid residual (mm, intraop frame), known at
//                          every preop mesh node from the elastic solve and
//                          interpolated linearly inside each tet.
//   Pull-back field on the intraop grid (what is written as field.nii.gz):
//     u(x) such that x + u(x) = phi^-1(x), the matching preop point.
#include <Eigen/Dense>
#include <vector>

namespace brainshift {

struct MeshDeformation {
  Eigen::Matrix4d intraop_from_preop = Eigen::Matrix4d::Identity();
  // One per TetMesh node: phi(p_i) - intraop_from_preop * p_i, in mm.
  std::vector<Eigen::Vector3d> nonrigid_mm;

  Eigen::Vector3d apply_affine(const Eigen::Vector3d& preop_mm) const {
    return (intraop_from_preop * preop_mm.homogeneous()).head<3>();
  }
  // phi at node i.
  Eigen::Vector3d node_intraop_mm(const Eigen::Vector3d& preop_mm, std::size_t i) const {
    return apply_affine(preop_mm) + nonrigid_mm[i];
  }
};

}  // namespace brainshift
