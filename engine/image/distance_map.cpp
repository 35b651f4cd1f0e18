// Separable exact Euclidean distance transform (Felzenszwalb & Huttenlocher,
// "Distance transforms of sampled functions", 2012), anisotropic spacing.
#include "image/distance_map.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace brainshift {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// First pass along x for a binary feature set: squared distance in mm^2 to the
// nearest feature voxel in the same row, by two linear sweeps.
template <class IsFeature>
void row_pass(const Grid3& g, double sx, IsFeature&& is_feature, std::vector<float>& out) {
  const int nx = g.dims[0];
  std::vector<int> gap(nx);
  const int far = std::numeric_limits<int>::max() / 4;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j) {
      const std::size_t base = g.index(0, j, k);
      int last = -far;
      for (int i = 0; i < nx; ++i) {
        if (is_feature(base + i)) last = i;
        gap[i] = i - last;
      }
      last = far + nx;
      for (int i = nx - 1; i >= 0; --i) {
        if (is_feature(base + i)) last = i;
        const int d = std::min(gap[i], last - i);
        out[base + i] = d >= far / 2 ? kInf : static_cast<float>(d * sx * d * sx);
      }
    }
}

// Lower envelope of parabolas on one line: d[q] = min_p (s^2 (q-p)^2 + f[p]).
class LinePass {
 public:
  explicit LinePass(int n) : f_(n), v_(n), z_(n + 1) {}

  void run(float* data, std::size_t n, std::size_t stride, double spacing) {
    const double s2 = spacing * spacing;
    for (std::size_t q = 0; q < n; ++q) f_[q] = data[q * stride];
    int k = -1;
    for (int q = 0; q < static_cast<int>(n); ++q) {
      if (std::isinf(f_[q])) continue;  // infinite parabolas never touch the envelope
      const double fq = f_[q] + s2 * q * q;
      while (k >= 0) {
        const int p = v_[k];
        const double s = (fq - (f_[p] + s2 * p * p)) / (2.0 * s2 * (q - p));
        if (s > z_[k]) {
          z_[k + 1] = s;
          break;
        }
        --k;
      }
      if (k < 0) z_[0] = -std::numeric_limits<double>::infinity();
      ++k;
      v_[k] = q;
      if (k == 0) z_[0] = -std::numeric_limits<double>::infinity();
      z_[k + 1] = std::numeric_limits<double>::infinity();
    }
    if (k < 0) return;  // whole line infinite: leave as is
    int j = 0;
    for (std::size_t q = 0; q < n; ++q) {
      while (z_[j + 1] < static_cast<double>(q)) ++j;
      const double dq = static_cast<double>(q) - v_[j];
      data[q * stride] = static_cast<float>(s2 * dq * dq + f_[v_[j]]);
    }
  }

 private:
  std::vector<double> f_;
  std::vector<int> v_;
  std::vector<double> z_;
};

template <class IsFeature>
ImageF squared_edt(const Grid3& g, IsFeature&& is_feature) {
  ImageF out(g);
  if (g.voxel_count() == 0) return out;
  const Eigen::Vector3d sp = g.spacing_mm();
  row_pass(g, sp[0], is_feature, out.voxels);
  const int nx = g.dims[0], ny = g.dims[1], nz = g.dims[2];
  float* d = out.voxels.data();
  // Lines along y and z are strided in memory; each slab is transposed into a
  // buffer where those lines are contiguous (3-4x faster than strided access).
  std::vector<float> buf(static_cast<std::size_t>(nx) * std::max(ny, nz));
  LinePass along_y(ny);
  for (int k = 0; k < nz; ++k) {
    float* slice = d + g.index(0, 0, k);
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) buf[static_cast<std::size_t>(i) * ny + j] = slice[static_cast<std::size_t>(j) * nx + i];
    for (int i = 0; i < nx; ++i) along_y.run(buf.data() + static_cast<std::size_t>(i) * ny, ny, 1, sp[1]);
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) slice[static_cast<std::size_t>(j) * nx + i] = buf[static_cast<std::size_t>(i) * ny + j];
  }
  if (nz > 1) {
    LinePass along_z(nz);
    for (int j = 0; j < ny; ++j) {
      for (int k = 0; k < nz; ++k) {
        const float* row = d + g.index(0, j, k);
        for (int i = 0; i < nx; ++i) buf[static_cast<std::size_t>(i) * nz + k] = row[i];
      }
      for (int i = 0; i < nx; ++i) along_z.run(buf.data() + static_cast<std::size_t>(i) * nz, nz, 1, sp[2]);
      for (int k = 0; k < nz; ++k) {
        float* row = d + g.index(0, j, k);
        for (int i = 0; i < nx; ++i) row[i] = buf[static_cast<std::size_t>(i) * nz + k];
      }
    }
  }
  return out;
}

}  // namespace

ImageF squared_distance_to_mask_mm2(const Mask& mask) {
  const std::uint8_t* m = mask.voxels.data();
  return squared_edt(mask.grid, [m](std::size_t i) { return m[i] != 0; });
}

ImageF distance_to_mask_mm(const Mask& mask) {
  ImageF d = squared_distance_to_mask_mm2(mask);
  for (float& v : d.voxels) v = std::sqrt(v);
  return d;
}

ImageF signed_distance_mm(const Mask& mask) {
  const std::uint8_t* m = mask.voxels.data();
  ImageF out = squared_edt(mask.grid, [m](std::size_t i) { return m[i] != 0; });
  const ImageF in = squared_edt(mask.grid, [m](std::size_t i) { return m[i] == 0; });
  const float half = static_cast<float>(0.5 * mask.grid.spacing_mm().minCoeff());
  for (std::size_t i = 0; i < out.voxels.size(); ++i)
    out.voxels[i] = m[i] ? -(std::sqrt(in.voxels[i]) - half) : std::sqrt(out.voxels[i]) - half;
  return out;
}

}  // namespace brainshift
