#pragma once
// Trilinear sampling of a scalar image together with its analytic gradient, in
// world RAS+ mm. Used on signed distance maps by the affine and active-surface
// stages: the gradient of the interpolant is what Gauss-Newton linearises.
#include <Eigen/Dense>
#include <cmath>

#include "core/image.h"

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
    const Eigen::Vector3d v = linear_ * world_mm + offset_;
    const auto& dims = image_.grid.dims;
    int base[3];
    double frac[3];
    for (int a = 0; a < 3; ++a) {
      if (!(v[a] >= 0.0 && v[a] <= dims[a] - 1.0) || dims[a] < 2) return false;
      base[a] = std::min(static_cast<int>(v[a]), dims[a] - 2);
      frac[a] = v[a] - base[a];
    }
    const std::size_t sx = 1, sy = static_cast<std::size_t>(dims[0]),
                      sz = sy * static_cast<std::size_t>(dims[1]);
    const float* p = image_.voxels.data() + image_.grid.index(base[0], base[1], base[2]);
    const double c000 = p[0], c100 = p[sx], c010 = p[sy], c110 = p[sx + sy];
    const double c001 = p[sz], c101 = p[sx + sz], c011 = p[sy + sz], c111 = p[sx + sy + sz];
    if (!std::isfinite(c000 + c100 + c010 + c110 + c001 + c101 + c011 + c111)) return false;
    const double fx = frac[0], fy = frac[1], fz = frac[2];
    // Bilinear in (y,z) of the x-edges, etc.: the exact partial derivatives.
    const double c00 = c000 + fx * (c100 - c000), c10 = c010 + fx * (c110 - c010);
    const double c01 = c001 + fx * (c101 - c001), c11 = c011 + fx * (c111 - c011);
    const double c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
    *value = c0 + fz * (c1 - c0);
    if (gradient_mm) {
      const double dx00 = c100 - c000, dx10 = c110 - c010, dx01 = c101 - c001, dx11 = c111 - c011;
      const double dx0 = dx00 + fy * (dx10 - dx00), dx1 = dx01 + fy * (dx11 - dx01);
      Eigen::Vector3d g_voxel(dx0 + fz * (dx1 - dx0), (c10 - c00) + fz * ((c11 - c01) - (c10 - c00)),
                              c1 - c0);
      // d/dworld = (d voxel / d world)^T d/dvoxel.
      *gradient_mm = linear_.transpose() * g_voxel;
    }
    return true;
  }

 private:
  const ImageF& image_;
  Eigen::Matrix4d voxel_from_world_;
  Eigen::Matrix3d linear_;
  Eigen::Vector3d offset_;
};

}  // namespace brainshift
