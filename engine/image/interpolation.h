#pragma once
// The project's one interpolation on continuous voxel coordinates (voxel
// (i,j,k) has its centre at (i,j,k)): trilinear for scalar images and 3-vector
// fields, nearest for labels. Callers convert world RAS+ mm to voxel
// coordinates themselves, once per grid (image/resample.h GridSampler,
// registration/linear_sampler.h), so the per-point cost is the cell alone.
//
// Header-only: it runs per voxel on the per-scan paths (warping, resampling,
// registration, composing fields), where a call across libraries would cost
// more than the interpolation (brainshift_sampler_bench).
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>

#include "core/image.h"

namespace brainshift {

// What happens at the edges of a grid of n voxels along an axis. The rules
// agree inside the hull of voxel centres [0, n-1]; they differ outside it.
enum class TrilinearEdge {
  // Sampled on [-0.5, n-0.5], the voxels' extent: within the outer half voxel
  // the edge value is replicated; farther out nothing is sampled (the caller
  // returns its outside value). Resampling, warping, field sampling, the
  // phantom: an image covers its voxels, not only the hull of their centres.
  kVoxelExtent,
  // Sampled on [0, n-1] only, where a whole cell exists (needs n >= 2);
  // outside, nothing is sampled. Registration: the gradient of the
  // interpolant must be that of a real cell, not of a replicated edge.
  kCentreHull,
  // Sampled everywhere, the coordinate clamped onto [0, n-1] (needs n >= 2).
  // Composing a field with itself, where every point needs a value.
  kClamp,
};

// A point's cell: the low corner, the offsets to the high corners and the
// position within.
template <class Real>
struct TrilinearCell {
  std::size_t origin = 0;             // voxel index of the low corner
  std::array<std::size_t, 3> step{};  // index offset to the high corner per axis (0: the edge replicated)
  std::array<Real, 3> t{};            // position in the cell per axis, in [0, 1]
};

// Locates voxel coordinate v (any Eigen 3-vector; the arithmetic is in its
// scalar type, the fractions then rounded to Real). False where Edge samples
// nothing (never for kClamp); NaN is outside under kVoxelExtent and
// kCentreHull.
template <TrilinearEdge Edge, class Real, class Coord>
inline bool trilinear_cell(const Grid3& grid, const Coord& v, TrilinearCell<Real>* cell) {
  using S = typename Coord::Scalar;
  const auto& n = grid.dims;
  const std::size_t stride[3] = {1, static_cast<std::size_t>(n[0]),
                                 static_cast<std::size_t>(n[0]) * static_cast<std::size_t>(n[1])};
  int lo[3];
  for (int a = 0; a < 3; ++a) {
    const S top = static_cast<S>(n[a] - 1);
    if constexpr (Edge == TrilinearEdge::kVoxelExtent) {
      if (!(v[a] >= S(-0.5) && v[a] <= top + S(0.5))) return false;
      const S c = std::clamp(v[a], S(0), top);
      lo[a] = std::min(static_cast<int>(c), n[a] - 1);
      cell->step[a] = lo[a] < n[a] - 1 ? stride[a] : 0;
      cell->t[a] = static_cast<Real>(c - static_cast<S>(lo[a]));
    } else {
      if constexpr (Edge == TrilinearEdge::kCentreHull) {
        if (!(v[a] >= S(0) && v[a] <= top) || n[a] < 2) return false;
      }
      const S c = Edge == TrilinearEdge::kClamp ? std::clamp(v[a], S(0), top) : v[a];
      // The last cell takes the far face (t = 1), so every cell is whole.
      lo[a] = std::min(static_cast<int>(c), n[a] - 2);
      cell->step[a] = stride[a];
      cell->t[a] = static_cast<Real>(c - static_cast<S>(lo[a]));
    }
  }
  cell->origin = grid.index(lo[0], lo[1], lo[2]);
  return true;
}

namespace interpolation_detail {
// The value type a voxel of type T is interpolated in: Real for scalars, a
// 3-vector of Real for vector fields.
template <class Real, class T>
struct Value {
  using type = Real;
  static Real of(T v) { return static_cast<Real>(v); }
};
template <class Real>
struct Value<Real, Eigen::Vector3f> {
  using type = Eigen::Matrix<Real, 3, 1>;
  static type of(const Eigen::Vector3f& v) { return v.template cast<Real>(); }
};
}  // namespace interpolation_detail

template <class Real, class T>
using TrilinearValue = typename interpolation_detail::Value<Real, T>::type;

// The cell's 8 corner values, x fastest: corner[dx + 2 dy + 4 dz].
template <class Real, class T>
inline std::array<TrilinearValue<Real, T>, 8> trilinear_corners(const T* voxels, const TrilinearCell<Real>& c) {
  using V = interpolation_detail::Value<Real, T>;
  const T* p = voxels + c.origin;
  const std::size_t x = c.step[0], y = c.step[1], z = c.step[2];
  return {V::of(p[0]), V::of(p[x]), V::of(p[y]), V::of(p[x + y]),
          V::of(p[z]), V::of(p[x + z]), V::of(p[y + z]), V::of(p[x + y + z])};
}

// The interpolant, as a + t (b - a) along x, then y, then z: exact at the low
// corner (t = 0) and for constant data; at t = 1 to rounding of b - a.
template <class V, class Real>
inline V trilinear_blend(const std::array<V, 8>& c, const TrilinearCell<Real>& cell) {
  const Real fx = cell.t[0], fy = cell.t[1], fz = cell.t[2];
  const V c00 = c[0] + fx * (c[1] - c[0]), c10 = c[2] + fx * (c[3] - c[2]);
  const V c01 = c[4] + fx * (c[5] - c[4]), c11 = c[6] + fx * (c[7] - c[6]);
  const V c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
  return c0 + fz * (c1 - c0);
}

// The interpolant of scalar corners and its exact partial derivatives along
// the voxel axes (what Gauss-Newton linearises). Along an axis whose edge is
// replicated (kVoxelExtent, outer half voxel) the derivative is 0.
template <class Real>
inline Real trilinear_blend_gradient(const std::array<Real, 8>& c, const TrilinearCell<Real>& cell,
                                     Eigen::Matrix<Real, 3, 1>* d_voxel) {
  const Real fx = cell.t[0], fy = cell.t[1], fz = cell.t[2];
  const Real c00 = c[0] + fx * (c[1] - c[0]), c10 = c[2] + fx * (c[3] - c[2]);
  const Real c01 = c[4] + fx * (c[5] - c[4]), c11 = c[6] + fx * (c[7] - c[6]);
  const Real c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
  // Bilinear in (y, z) of the x-edges' differences, and so on.
  const Real dx00 = c[1] - c[0], dx10 = c[3] - c[2], dx01 = c[5] - c[4], dx11 = c[7] - c[6];
  const Real dx0 = dx00 + fy * (dx10 - dx00), dx1 = dx01 + fy * (dx11 - dx01);
  *d_voxel = {dx0 + fz * (dx1 - dx0), (c10 - c00) + fz * ((c11 - c01) - (c10 - c00)), c1 - c0};
  return c0 + fz * (c1 - c0);
}

// Trilinear value of voxels (on grid) at voxel coordinate v; false, and
// *value untouched, where Edge samples nothing.
template <TrilinearEdge Edge, class Real = double, class T, class Coord>
inline bool trilinear_sample(const Grid3& grid, const T* voxels, const Coord& v, TrilinearValue<Real, T>* value) {
  TrilinearCell<Real> cell;
  if (!trilinear_cell<Edge>(grid, v, &cell)) return false;
  *value = trilinear_blend(trilinear_corners<Real>(voxels, cell), cell);
  return true;
}

// Index of the voxel nearest to v (halves round up), with the kVoxelExtent
// rule: the outer half voxel belongs to the edge voxel, farther out is
// outside (false). Labels, which must not be blended.
inline bool nearest_voxel(const Grid3& grid, const Eigen::Vector3d& v, std::size_t* index) {
  const auto& n = grid.dims;
  int idx[3];
  for (int a = 0; a < 3; ++a) {
    if (!(v[a] >= -0.5 && v[a] <= n[a] - 0.5)) return false;
    idx[a] = std::clamp(static_cast<int>(std::floor(v[a] + 0.5)), 0, n[a] - 1);
  }
  *index = grid.index(idx[0], idx[1], idx[2]);
  return true;
}

}  // namespace brainshift
