#pragma once
// The intensity refinement's control lattice (registration/intensity_refinement.h):
// the correction v is trilinear on it. Internal to the refinement.
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

#include "core/image.h"
#include "image/image_stats.h"

namespace brainshift::intensity {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using Vec3f = Eigen::Vector3f;

// Nodes on the intraop voxel axes (so a voxel's cell is found without a
// matrix product), spacing_mm apart in every direction.
class Lattice {
 public:
  struct Cell {
    int base = 0;  // node of the cell's lowest corner
    float fx = 0, fy = 0, fz = 0;
  };

  Lattice(const VoxelBox& box, const Grid3& grid, double spacing_mm) : spacing_mm_(spacing_mm) {
    const Vec3 voxel_mm = grid.spacing_mm();
    for (int a = 0; a < 3; ++a) {
      origin_[a] = box.lo[a];
      step_[a] = spacing_mm / voxel_mm[a];
      n_[a] = static_cast<int>(std::floor((box.hi[a] - box.lo[a]) / step_[a])) + 2;
      lo_[a] = box.lo[a];
      extent_[a] = std::max(1, box.hi[a] - box.lo[a]);
    }
    coef_mm.assign(size(), Vec3::Zero());
  }

  std::size_t size() const { return static_cast<std::size_t>(n_[0]) * n_[1] * n_[2]; }
  int dim(int a) const { return n_[a]; }
  int node(int a, int b, int c) const { return a + n_[0] * (b + n_[1] * c); }
  double spacing_mm() const { return spacing_mm_; }

  Cell locate(double i, double j, double k) const {
    const double t[3] = {(i - origin_[0]) / step_[0], (j - origin_[1]) / step_[1], (k - origin_[2]) / step_[2]};
    int b[3];
    float f[3];
    for (int a = 0; a < 3; ++a) {
      b[a] = std::min(static_cast<int>(std::max(t[a], 0.0)), n_[a] - 2);  // floor for t >= 0
      f[a] = static_cast<float>(std::clamp(t[a] - b[a], 0.0, 1.0));
    }
    return {node(b[0], b[1], b[2]), f[0], f[1], f[2]};
  }

  // fn(node, weight) for the 8 corners of a cell (trilinear weights, sum 1).
  template <class Fn>
  void for_corners(const Cell& c, Fn&& fn) const {
    const int sy = n_[0], sz = n_[0] * n_[1];
    const double wx[2] = {1.0 - c.fx, c.fx}, wy[2] = {1.0 - c.fy, c.fy}, wz[2] = {1.0 - c.fz, c.fz};
    for (int dz = 0; dz < 2; ++dz)
      for (int dy = 0; dy < 2; ++dy)
        for (int dx = 0; dx < 2; ++dx) fn(c.base + dx + sy * dy + sz * dz, wx[dx] * wy[dy] * wz[dz]);
  }

  Vec3 value(const Cell& c) const {
    Vec3 v = Vec3::Zero();
    for_corners(c, [&](int n, double w) { v += w * coef_mm[n]; });
    return v;
  }

  // v along the voxel row (., j, k) at the lattice's x nodes, blended across
  // the other two axes once per row; row_weights interpolates along the row.
  void row(int j, int k, std::vector<Eigen::Vector3f>* line) const {
    const Cell c = locate(origin_[0], j, k);
    const int sy = n_[0], sz = n_[0] * n_[1];
    const double w[4] = {(1.0 - c.fy) * (1.0 - c.fz), c.fy * (1.0 - c.fz), (1.0 - c.fy) * c.fz, c.fy * c.fz};
    const int off[4] = {0, sy, sz, sy + sz};
    line->resize(static_cast<std::size_t>(n_[0]));
    for (int a = 0; a < n_[0]; ++a) {
      Vec3 v = Vec3::Zero();
      for (int q = 0; q < 4; ++q) v += w[q] * coef_mm[c.base + a + off[q]];
      (*line)[a] = v.cast<float>();
    }
  }
  // Cell and weight along x of every voxel i in [lo, hi] (the same for all rows).
  void row_weights(int lo, int hi, std::vector<int>* cell, std::vector<float>* frac) const {
    cell->clear();
    frac->clear();
    for (int i = lo; i <= hi; ++i) {
      const Cell c = locate(i, origin_[1], origin_[2]);
      cell->push_back(c.base);  // node (b, 0, 0) == b
      frac->push_back(c.fx);
    }
  }

  // Position in [-1, 1]^3 over the lattice's voxel box: the bias polynomial's
  // argument (well conditioned whatever the grid).
  Eigen::Vector3f normalised(int i, int j, int k) const {
    return {static_cast<float>(2.0 * (i - lo_[0]) / extent_[0] - 1.0),
            static_cast<float>(2.0 * (j - lo_[1]) / extent_[1] - 1.0),
            static_cast<float>(2.0 * (k - lo_[2]) / extent_[2] - 1.0)};
  }

  std::vector<Vec3> coef_mm;

 private:
  double spacing_mm_;
  Vec3 origin_, step_;
  std::array<int, 3> n_{}, lo_{}, extent_{};
};

// One pass over the grid: where v is used (within fade_mm of the brain
// region, whose distance is negative inside) and where background or cavity
// voxels lie inside the brain region (a resection cavity).
struct Boxes {
  VoxelBox region, foreign;
};

Boxes find_boxes(const ImageF& sdf_mm, const LabelImage& labels, std::uint16_t background, double fade_mm);

}  // namespace brainshift::intensity
