#pragma once
// Regular 3-D images on a voxel grid placed in world space (NIfTI RAS+ mm).
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace brainshift {

// Voxel (i,j,k) has its centre at world_from_voxel * (i,j,k,1), in RAS+ mm.
struct Grid3 {
  std::array<int, 3> dims{0, 0, 0};
  Eigen::Matrix4d world_from_voxel = Eigen::Matrix4d::Identity();

  std::size_t voxel_count() const {
    return static_cast<std::size_t>(dims[0]) * dims[1] * dims[2];
  }
  // x fastest, as NIfTI stores voxels.
  std::size_t index(int i, int j, int k) const {
    return static_cast<std::size_t>(i) +
           static_cast<std::size_t>(dims[0]) * (static_cast<std::size_t>(j) +
                                                static_cast<std::size_t>(dims[1]) * k);
  }
  bool contains(int i, int j, int k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < dims[0] && j < dims[1] && k < dims[2];
  }
  Eigen::Vector3d spacing_mm() const {
    return world_from_voxel.topLeftCorner<3, 3>().colwise().norm().transpose();
  }
  Eigen::Matrix4d voxel_from_world() const { return world_from_voxel.inverse(); }
  Eigen::Vector3d world_mm(double i, double j, double k) const {
    return (world_from_voxel * Eigen::Vector4d(i, j, k, 1.0)).head<3>();
  }
  // The one grid-compatibility test of the project (`register`, the daemon's
  // checks of pushed and uploaded images, the engine's input checks): same
  // dims, and no voxel centre placed farther apart by the two affines than
  // kSameGridVoxelFraction of the smaller voxel size.
  bool same_geometry(const Grid3& other) const {
    return dims == other.dims && max_voxel_offset_mm(other) <= same_grid_tolerance_mm(other);
  }
  // 1/100 of a voxel, relative to the voxel because the question is whether
  // voxel (i,j,k) of two images is the same place: a hundredth of a voxel moves
  // no label and no interpolated intensity measurably (our accuracy is tenths
  // of a mm), while float32 rounding of a NIfTI-1 sform or qform (relative
  // 6e-8: about 2e-5 mm at the far corner of a 256-voxel, 1 mm grid 100 mm from
  // the origin) stays some 500 times below it. Any real mismatch (a
  // resampled or re-oriented image) is a whole voxel or more.
  static constexpr double kSameGridVoxelFraction = 1e-2;
  double same_grid_tolerance_mm(const Grid3& other) const {
    return kSameGridVoxelFraction * std::min(spacing_mm().minCoeff(), other.spacing_mm().minCoeff());
  }
  // Largest distance in mm between the world positions the two affines give
  // one voxel of this grid. The difference of two affines is affine and its
  // norm convex, so the largest is at one of the 8 corner voxels.
  double max_voxel_offset_mm(const Grid3& other) const {
    const Eigen::Matrix4d d = world_from_voxel - other.world_from_voxel;
    double worst = 0.0;
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector4d v((c & 1) ? dims[0] - 1 : 0, (c & 2) ? dims[1] - 1 : 0, (c & 4) ? dims[2] - 1 : 0, 1.0);
      worst = std::max(worst, (d * v).head<3>().norm());
    }
    return worst;
  }
};

template <class T>
struct Image3 {
  Grid3 grid;
  std::vector<T> voxels;

  Image3() = default;
  explicit Image3(const Grid3& g, T fill = T{}) : grid(g), voxels(g.voxel_count(), fill) {}
  T& at(int i, int j, int k) { return voxels[grid.index(i, j, k)]; }
  const T& at(int i, int j, int k) const { return voxels[grid.index(i, j, k)]; }
};

using ImageF = Image3<float>;
// Label values of the project fit in 16 bits (atlases use a few hundred at most).
using LabelImage = Image3<std::uint16_t>;

// A 3-component vector per voxel (displacement fields), world RAS+ mm.
struct VectorImage3 {
  Grid3 grid;
  std::vector<Eigen::Vector3f> vectors;

  VectorImage3() = default;
  explicit VectorImage3(const Grid3& g)
      : grid(g), vectors(g.voxel_count(), Eigen::Vector3f::Zero()) {}
};

}  // namespace brainshift
