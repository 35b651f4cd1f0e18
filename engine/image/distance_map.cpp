// Separable exact Euclidean distance transform (Felzenszwalb & Huttenlocher,
// "Distance transforms of sampled functions", 2012), anisotropic spacing.
#include "image/distance_map.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "core/parallel.h"

namespace brainshift {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// First pass along x for a binary feature set: squared distance in mm^2 to the
// nearest feature voxel in the same row, by two linear sweeps.
template <class IsFeature>
void row_pass(const Grid3& g, double sx, IsFeature&& is_feature, std::vector<float>& out, double cap_mm2) {
  const int nx = g.dims[0];
  const int far = std::numeric_limits<int>::max() / 4;
  const std::size_t rows = static_cast<std::size_t>(g.dims[1]) * static_cast<std::size_t>(g.dims[2]);
  parallel_halves(rows, 64, [&](std::size_t r0, std::size_t r1) {
    std::vector<int> gap(nx);
    for (std::size_t r = r0; r < r1; ++r) {
      const std::size_t base = r * static_cast<std::size_t>(nx);
      int last = -far;
      for (int i = 0; i < nx; ++i) {
        if (is_feature(base + i)) last = i;
        gap[i] = i - last;
      }
      last = far + nx;
      for (int i = nx - 1; i >= 0; --i) {
        if (is_feature(base + i)) last = i;
        const int d = std::min(gap[i], last - i);
        const float d2 = static_cast<float>(d * sx * d * sx);
        out[base + i] = d >= far / 2 || d2 > cap_mm2 ? kInf : d2;
      }
    }
  });
}

// Lower envelope of parabolas on one line: d[q] = min_p (s^2 (q-p)^2 + f[p]).
// Works with g[p] = f[p] + s^2 p^2 so each intersection costs one division.
class LinePass {
 public:
  explicit LinePass(int n) : g_(n), v_(n), z_(n + 1) {}

  // Values above cap_mm2 become +infinity (see squared_edt).
  void run(float* data, int n, double spacing, double cap_mm2) {
    // A line of feature voxels only (zeros) is its own answer: every point is
    // its own nearest, and the envelope would give back exactly 0. Most lines
    // of the background's transform (the inside of a signed distance) are
    // such lines; skipping them changes no bit.
    if (std::all_of(data, data + n, [](float v) { return v == 0.f; })) return;
    const double s2 = spacing * spacing;
    int k = -1;
    for (int q = 0; q < n; ++q) {
      if (std::isinf(data[q])) continue;  // infinite parabolas never touch the envelope
      const double gq = data[q] + s2 * q * q;
      g_[q] = gq;
      double s = -std::numeric_limits<double>::infinity();
      while (k >= 0) {
        const int p = v_[k];
        s = (gq - g_[p]) / (2.0 * s2 * (q - p));
        if (s > z_[k]) break;
        --k;
      }
      ++k;
      v_[k] = q;
      z_[k] = k == 0 ? -std::numeric_limits<double>::infinity() : s;
      z_[k + 1] = std::numeric_limits<double>::infinity();
    }
    if (k < 0) return;  // whole line infinite: leave as is
    int j = 0;
    for (int q = 0; q < n; ++q) {
      while (z_[j + 1] < q) ++j;
      const int p = v_[j];
      const float d2 = static_cast<float>(g_[p] - s2 * p * p + s2 * (q - p) * (q - p));
      data[q] = d2 > cap_mm2 ? kInf : d2;
    }
  }

 private:
  std::vector<double> g_;
  std::vector<int> v_;
  std::vector<double> z_;
};

// dst (cols x rows) = transpose of src (rows x cols, row-major), in cache-sized tiles.
void transpose(const float* src, std::size_t rows, std::size_t cols, std::size_t src_stride, float* dst,
               std::size_t dst_stride) {
  constexpr std::size_t kTile = 16;
  for (std::size_t r0 = 0; r0 < rows; r0 += kTile)
    for (std::size_t c0 = 0; c0 < cols; c0 += kTile) {
      const std::size_t r1 = std::min(rows, r0 + kTile), c1 = std::min(cols, c0 + kTile);
      for (std::size_t r = r0; r < r1; ++r)
        for (std::size_t c = c0; c < c1; ++c) dst[c * dst_stride + r] = src[r * src_stride + c];
    }
}

// cap_mm2: squared distances up to it are exact, larger ones +infinity. A
// value above the cap after one pass stays above it after the next (each pass
// adds a square), so dropping it changes no value up to the cap; lines left
// all infinite cost nothing. Thresholding at the cap (a dilation, an erosion)
// needs no more.
template <class IsFeature>
ImageF squared_edt(const Grid3& g, IsFeature&& is_feature, double cap_mm2 = kInf) {
  ImageF out(g);
  if (g.voxel_count() == 0) return out;
  const Eigen::Vector3d sp = g.spacing_mm();
  row_pass(g, sp[0], is_feature, out.voxels, cap_mm2);
  const int nx = g.dims[0], ny = g.dims[1], nz = g.dims[2];
  float* d = out.voxels.data();
  // Lines along y and z are strided in memory; each slab is transposed into a
  // buffer where those lines are contiguous (3-4x faster than strided access).
  const std::size_t snx = nx, sny = ny, snz = nz, slab = snx * sny;
  // The OR machines have two cores and this sits on the intraop critical path.
  parallel_halves(snz, 8, [&](std::size_t k0, std::size_t k1) {
    LinePass along_y(ny);
    std::vector<float> buf(snx * sny);
    for (std::size_t k = k0; k < k1; ++k) {
      float* slice = d + k * slab;
      transpose(slice, sny, snx, snx, buf.data(), sny);  // buf: nx lines of ny
      for (std::size_t i = 0; i < snx; ++i) along_y.run(buf.data() + i * sny, ny, sp[1], cap_mm2);
      transpose(buf.data(), snx, sny, sny, slice, snx);
    }
  });
  if (nz == 1) return out;
  // The (x, z) plane at fixed y: rows of nx values, nx*ny apart.
  parallel_halves(sny, 8, [&](std::size_t j0, std::size_t j1) {
    LinePass along_z(nz);
    std::vector<float> buf(snx * snz);
    for (std::size_t j = j0; j < j1; ++j) {
      float* plane = d + j * snx;
      transpose(plane, snz, snx, slab, buf.data(), snz);  // buf: nx lines of nz
      for (std::size_t i = 0; i < snx; ++i) along_z.run(buf.data() + i * snz, nz, sp[2], cap_mm2);
      transpose(buf.data(), snx, snz, snz, plane, slab);
    }
  });
  return out;
}

}  // namespace

ImageF squared_distance_to_mask_mm2(const Mask& mask, double cap_mm2) {
  const std::uint8_t* m = mask.voxels.data();
  return squared_edt(mask.grid, [m](std::size_t i) { return m[i] != 0; }, cap_mm2);
}

ImageF squared_distance_to_mask_mm2(const Mask& mask) { return squared_distance_to_mask_mm2(mask, kInf); }

ImageF distance_to_mask_mm(const Mask& mask, double cap_mm) {
  ImageF d = squared_distance_to_mask_mm2(mask, cap_mm * cap_mm);
  for (float& v : d.voxels) v = std::sqrt(v);
  return d;
}

ImageF distance_to_mask_mm(const Mask& mask) { return distance_to_mask_mm(mask, kInf); }

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
