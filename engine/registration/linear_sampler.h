#pragma once
// Trilinear sampling of a scalar image together with its analytic gradient, in
// world RAS+ mm. Used on signed distance maps by the affine and active-surface
// stages: the gradient of the interpolant is what Gauss-Newton linearises.
// The interpolation is image/interpolation.h's, with the kCentreHull edge.
#include <Eigen/Dense>
#include <cmath>

#include "core/image.h"
#include "image/interpolation.h"

namespace brainshift {

class LinearSampler {
 public:
  // Keeps a reference: `image` must outlive the sampler.
  explicit LinearSampler(const ImageF& image)
      : image_(image),
        voxel_from_world_(image.grid.voxel_from_world()),
        linear_(voxel_from_world_.topLeftCorner<3, 3>()),
        offset_(voxel_from_world_.topRightCorner<3, 1>()) {}

  // Value and world-frame gradient (units of the image per mm) at world_mm.
  // Returns false (and leaves the outputs untouched) outside the hull of voxel
  // centres, where no trilinear cell exists, or where a corner is not finite
  // (distance maps of empty masks are infinite): the caller treats it as "no data".
  bool sample(const Eigen::Vector3d& world_mm, double* value, Eigen::Vector3d* gradient_mm) const {
    TrilinearCell<double> cell;
    if (!trilinear_cell<TrilinearEdge::kCentreHull>(image_.grid, Eigen::Vector3d(linear_ * world_mm + offset_), &cell))
      return false;
    const std::array<double, 8> c = trilinear_corners<double>(image_.voxels.data(), cell);
    if (!std::isfinite(c[0] + c[1] + c[2] + c[3] + c[4] + c[5] + c[6] + c[7])) return false;
    if (!gradient_mm) {
      *value = trilinear_blend(c, cell);
      return true;
    }
    Eigen::Vector3d d_voxel;
    *value = trilinear_blend_gradient(c, cell, &d_voxel);
    // d/dworld = (d voxel / d world)^T d/dvoxel.
    *gradient_mm = linear_.transpose() * d_voxel;
    return true;
  }

 private:
  const ImageF& image_;
  Eigen::Matrix4d voxel_from_world_;
  Eigen::Matrix3d linear_;
  Eigen::Vector3d offset_;
};

}  // namespace brainshift
