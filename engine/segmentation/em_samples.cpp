#include "segmentation/em_samples.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"

namespace brainshift::segmentation {
namespace {

// Lattice points along an axis of n voxels at this stride, started half a
// stride in.
std::size_t lattice_points(int n, int stride) { return n > stride / 2 ? (n - stride / 2 - 1) / stride + 1 : 0; }

// A regular subsample of at most `budget` voxels: a lattice of about the same
// spacing in mm along every axis (strides per axis from the voxel spacing),
// started half a stride in. Rounding the strides alone could take up to 3x
// the budget (a stride of 1.49 voxels rounds to 1) and the fit's time with
// it: the finest axis in mm is coarsened until the lattice fits, at most
// every axis's voxels (a bounded loop). A stride through the voxels in grid
// order aliases whenever it shares a factor with a row's length (a stride of
// 55 on rows of 220 voxels sees 4 sagittal planes and nothing between them).
std::array<int, 3> sample_strides(const Grid3& g, std::size_t budget) {
  const Eigen::Vector3d spacing = g.spacing_mm();
  const double volume_mm3 = static_cast<double>(g.voxel_count()) * spacing.prod();
  const double h_mm = std::cbrt(volume_mm3 / static_cast<double>(std::max<std::size_t>(budget, 1)));
  std::array<int, 3> stride{};
  for (int a = 0; a < 3; ++a) stride[a] = std::max(1, static_cast<int>(std::lround(h_mm / spacing[a])));
  const auto count = [&] {
    return lattice_points(g.dims[0], stride[0]) * lattice_points(g.dims[1], stride[1]) *
           lattice_points(g.dims[2], stride[2]);
  };
  while (count() > budget) {
    int finest = -1;
    for (int a = 0; a < 3; ++a)
      if (stride[a] < g.dims[a] && (finest < 0 || stride[a] * spacing[a] < stride[finest] * spacing[finest])) finest = a;
    if (finest < 0) break;
    stride[finest] += 1;
  }
  return stride;
}

}  // namespace

Samples draw_samples(const ImageF& image, const TissuePrior& prior, double scale, std::size_t budget) {
  const auto& g = image.grid;
  const std::array<int, 3> stride = sample_strides(g, budget);
  Samples s;
  for (int k = stride[2] / 2; k < g.dims[2]; k += stride[2])
    for (int j = stride[1] / 2; j < g.dims[1]; j += stride[1])
      for (int i = stride[0] / 2; i < g.dims[0]; i += stride[0]) {
        const std::size_t v = g.index(i, j, k);
        s.voxel.push_back({i, j, k});
        s.intensity.push_back(image.voxels[v] / scale);
        std::array<double, kTissues> lp{};
        for (int t = 0; t < kTissues; ++t) lp[t] = prior.p[t][v] > 0 ? std::log(prior.p[t][v]) : kLogTiny;
        s.log_prior.push_back(lp);
        s.band.push_back(in_surface_band(brain_prior_at(prior, v)));
        s.inside.push_back(std::exp(lp[0]) + std::exp(lp[1]));
      }
  return s;
}

// Intensity scale: the 99th percentile inside the prior's brain, so the
// numbers the fit works with are of order 1 for any scanner's units.
double brain_intensity_scale(const ImageF& image, const TissuePrior& prior) {
  std::vector<float> inside;
  for (std::size_t v = 0; v < image.voxels.size(); ++v)
    if (prior.p[0][v] + prior.p[1][v] > 0.5f) inside.push_back(image.voxels[v]);
  if (inside.empty()) throw InputError("segmentation: the prior places no brain in the image");
  const std::size_t at = static_cast<std::size_t>(0.99 * (inside.size() - 1));
  std::nth_element(inside.begin(), inside.begin() + static_cast<std::ptrdiff_t>(at), inside.end());
  const double scale = inside[at];
  if (!(scale > 0)) throw InputError("segmentation: the image is empty or not positive inside the brain");
  return scale;
}

}  // namespace brainshift::segmentation
