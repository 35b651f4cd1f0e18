#include "segmentation/head_mask.h"

#include <algorithm>
#include <array>
#include <cmath>

#include "image/resample.h"

namespace brainshift::segmentation {

float otsu_threshold(const std::vector<float>& values) {
  if (values.empty()) return 0.f;
  const auto [lo_it, hi_it] = std::minmax_element(values.begin(), values.end());
  const double lo = *lo_it, hi = *hi_it;
  if (!(hi > lo)) return static_cast<float>(hi);
  constexpr int kBins = 256;
  std::array<double, kBins> hist{};
  for (float v : values) hist[static_cast<std::size_t>(std::min(kBins - 1.0, (v - lo) / (hi - lo) * kBins))] += 1;
  double total = 0, sum = 0;
  for (int b = 0; b < kBins; ++b) {
    total += hist[b];
    sum += b * hist[b];
  }
  double w0 = 0, s0 = 0, best = -1;
  int best_bin = 0;
  for (int b = 0; b < kBins - 1; ++b) {
    w0 += hist[b];
    s0 += b * hist[b];
    const double w1 = total - w0;
    if (w0 <= 0 || w1 <= 0) continue;
    const double m0 = s0 / w0, m1 = (sum - s0) / w1;
    const double between = w0 * w1 * (m0 - m1) * (m0 - m1);
    if (between > best) {
      best = between;
      best_bin = b;
    }
  }
  return static_cast<float>(lo + (best_bin + 1.0) / kBins * (hi - lo));
}

namespace {

// The head mask's own grid of about spacing_mm: the same orientation, voxel
// 0 centred on the fine voxels it covers, reaching up to a coarse voxel
// past the image. Only the mask's threshold and closing see it; a grid
// that must span the image's extent exactly (labels coarsened by cover,
// fields carried back) is image/resample.h's working_grid.
Grid3 coarse_grid(const Grid3& grid, double spacing_mm) {
  const Eigen::Vector3d s = grid.spacing_mm();
  Grid3 out;
  Eigen::Matrix4d fine_from_coarse = Eigen::Matrix4d::Identity();
  for (int a = 0; a < 3; ++a) {
    const double r = std::max(1.0, spacing_mm / s[a]);
    out.dims[a] = std::max(1, static_cast<int>(std::ceil(grid.dims[a] / r)));
    fine_from_coarse(a, a) = r;
    fine_from_coarse(a, 3) = (r - 1) / 2;
  }
  out.world_from_voxel = grid.world_from_voxel * fine_from_coarse;
  return out;
}

}  // namespace

Mask head_mask(const ImageF& image, double coarse_mm, double closing_mm) {
  const Grid3 g = coarse_grid(image.grid, coarse_mm);
  const ImageF coarse = resample_linear(image, g);
  // Exact zeros are padding (outside a resampled or masked acquisition), not
  // air's noise: left out, they would make the threshold split padding from
  // everything else.
  std::vector<float> signal;
  signal.reserve(coarse.voxels.size());
  for (float v : coarse.voxels)
    if (v > 0) signal.push_back(v);
  const float t = otsu_threshold(signal);
  Mask head = threshold(coarse, t, std::numeric_limits<float>::max());
  head = largest_component(head, 6);
  head = fill_holes(close(head, closing_mm));
  return head;
}

}  // namespace brainshift::segmentation
