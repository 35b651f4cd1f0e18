// Threshold + morphology + seeded region growing (threshold_segmenter.h).
#include "phantom/threshold_segmenter.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "phantom/phantom_artefacts.h"
#include "phantom/phantom_support.h"

namespace brainshift {
namespace {

using phantom_detail::quantile;

// The candidate voxel nearest to `point` within radius_mm, or -1.
std::ptrdiff_t nearest_candidate(const Mask& candidates, const Eigen::Vector3d& point, double radius_mm) {
  const Grid3& g = candidates.grid;
  const Eigen::Vector3d c = (g.voxel_from_world() * point.homogeneous()).head<3>();
  const Eigen::Vector3d sp = g.spacing_mm();
  int lo[3], hi[3];
  for (int a = 0; a < 3; ++a) {
    lo[a] = std::max(0, static_cast<int>(std::floor(c[a] - radius_mm / sp[a])));
    hi[a] = std::min(g.dims[a] - 1, static_cast<int>(std::ceil(c[a] + radius_mm / sp[a])));
  }
  std::ptrdiff_t best = -1;
  double best_d = radius_mm;
  for (int k = lo[2]; k <= hi[2]; ++k)
    for (int j = lo[1]; j <= hi[1]; ++j)
      for (int i = lo[0]; i <= hi[0]; ++i) {
        if (!candidates.at(i, j, k)) continue;
        const double d = (g.world_mm(i, j, k) - point).norm();
        if (d <= best_d) best_d = d, best = static_cast<std::ptrdiff_t>(g.index(i, j, k));
      }
  return best;
}

}  // namespace

std::vector<double> otsu_thresholds(const std::vector<float>& values, int classes) {
  if (classes < 2 || classes > 8) throw InputError("multi-class Otsu: 2 to 8 classes");
  if (values.size() < static_cast<std::size_t>(classes)) throw InputError("multi-class Otsu: too few values");
  const double lo = quantile(values, 0.001), hi = quantile(values, 0.999);
  constexpr int kBins = 128;
  const double width = std::max(1e-12, (hi - lo) / kBins);
  std::vector<double> c_count(kBins + 1, 0.0), c_sum(kBins + 1, 0.0);
  {
    std::vector<double> count(kBins, 0.0);
    for (float v : values) count[std::clamp(static_cast<int>((v - lo) / width), 0, kBins - 1)] += 1;
    for (int b = 0; b < kBins; ++b) {
      c_count[b + 1] = c_count[b] + count[b];
      c_sum[b + 1] = c_sum[b] + count[b] * (lo + (b + 0.5) * width);
    }
  }
  // Between-class variance = sum over classes of n_k mean_k^2 - const:
  // maximised over contiguous bin ranges by dynamic programming.
  auto term = [&](int from, int to) {
    const double n = c_count[to] - c_count[from], s = c_sum[to] - c_sum[from];
    return n > 0 ? s * s / n : 0.0;
  };
  std::vector<std::vector<double>> best(classes + 1, std::vector<double>(kBins + 1, -1.0));
  std::vector<std::vector<int>> cut(classes + 1, std::vector<int>(kBins + 1, 0));
  for (int b = 1; b <= kBins; ++b) best[1][b] = term(0, b);
  for (int k = 2; k <= classes; ++k)
    for (int b = k; b <= kBins; ++b)
      for (int a = k - 1; a < b; ++a) {
        const double score = best[k - 1][a] + term(a, b);
        if (score > best[k][b]) best[k][b] = score, cut[k][b] = a;
      }
  std::vector<double> thresholds(classes - 1);
  for (int k = classes, b = kBins; k >= 2; --k) {
    b = cut[k][b];
    thresholds[k - 2] = lo + b * width;
  }
  return thresholds;
}

Mask fill_holes_per_slice(const Mask& mask) {
  const Grid3& g = mask.grid;
  Mask out = mask;
  std::vector<std::uint8_t> outside(static_cast<std::size_t>(g.dims[0]) * g.dims[1]);
  std::vector<std::pair<int, int>> stack;
  for (int k = 0; k < g.dims[2]; ++k) {
    std::fill(outside.begin(), outside.end(), 0);
    auto push = [&](int i, int j) {
      const std::size_t s = static_cast<std::size_t>(i) + static_cast<std::size_t>(g.dims[0]) * j;
      if (outside[s] || mask.at(i, j, k)) return;
      outside[s] = 1;
      stack.emplace_back(i, j);
    };
    for (int i = 0; i < g.dims[0]; ++i) push(i, 0), push(i, g.dims[1] - 1);
    for (int j = 0; j < g.dims[1]; ++j) push(0, j), push(g.dims[0] - 1, j);
    while (!stack.empty()) {
      const auto [i, j] = stack.back();
      stack.pop_back();
      if (i > 0) push(i - 1, j);
      if (i + 1 < g.dims[0]) push(i + 1, j);
      if (j > 0) push(i, j - 1);
      if (j + 1 < g.dims[1]) push(i, j + 1);
    }
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        if (!outside[static_cast<std::size_t>(i) + static_cast<std::size_t>(g.dims[0]) * j]) out.at(i, j, k) = 1;
  }
  return out;
}

ThresholdSegmentation segment_by_threshold(const ImageF& image, const SegmenterPrior& prior,
                                           const ThresholdSegmenterSpec& spec) {
  for (const Mask* m : {prior.brain, prior.ventricles})
    if (m && !m->grid.same_geometry(image.grid))
      throw InputError("threshold segmenter: the expected brain and ventricles must be on the image's grid");
  const auto& ventricle_points_mm = prior.ventricle_points_mm;
  if (image.grid.voxel_count() == 0 || image.voxels.size() != image.grid.voxel_count())
    throw InputError("threshold segmenter: the image is empty");
  if (!(spec.smoothing_mm >= 0 && spec.opening_mm >= 0 && spec.closing_mm >= 0 && spec.ventricle_margin_mm >= 0 &&
        spec.seed_search_mm > 0 && spec.roi_margin_mm >= 0 && spec.ventricle_roi_margin_mm >= 0 && spec.brain_label != 0 && spec.ventricle_label != 0 &&
        spec.brain_label != spec.ventricle_label))
    throw InputError("threshold segmenter: radii >= 0, seed search > 0 and two distinct non-zero labels are required");
  const Grid3& g = image.grid;
  const Eigen::Vector3d sp = g.spacing_mm();
  ImageF smooth = image;
  gaussian_smooth_voxels(smooth, Eigen::Vector3d(spec.smoothing_mm / sp.x(), spec.smoothing_mm / sp.y(), spec.smoothing_mm / sp.z()));
  // Four classes: air | bone and CSF | grey | white matter and fat on a T1;
  // air and bone | white | grey | CSF on a T2-like image.
  const std::vector<double> t = otsu_thresholds(smooth.voxels, 4);
  const bool t1 = spec.contrast != Contrast::t2_like;  // dark CSF: enhanced or not, or FLAIR
  const double low = t1 ? t[1] : t[0], high = t1 ? t[2] : t[2];

  Mask candidate(g, 0), csf(g, 0);
  for (std::size_t v = 0; v < candidate.voxels.size(); ++v) {
    const float s = smooth.voxels[v];
    candidate.voxels[v] = t1 ? s >= low : (s >= low && s < high);
    csf.voxels[v] = t1 ? s < low : s >= high;
  }
  if (prior.brain) {
    const Mask roi = dilate(*prior.brain, spec.roi_margin_mm);
    for (std::size_t v = 0; v < candidate.voxels.size(); ++v) candidate.voxels[v] = candidate.voxels[v] && roi.voxels[v];
  }
  Mask brain = largest_component(open(candidate, spec.opening_mm), 6);
  brain = fill_holes(close(fill_holes_per_slice(brain), spec.closing_mm));

  // Ventricles: CSF well inside the brain, grown from the seeds.
  Mask inner = erode(brain, spec.ventricle_margin_mm);
  if (prior.ventricles) {
    const Mask roi = dilate(*prior.ventricles, spec.ventricle_roi_margin_mm);
    for (std::size_t v = 0; v < inner.voxels.size(); ++v) inner.voxels[v] = inner.voxels[v] && roi.voxels[v];
  }
  for (std::size_t v = 0; v < csf.voxels.size(); ++v) csf.voxels[v] = csf.voxels[v] && inner.voxels[v];
  int count = 0;
  const auto components = connected_components(csf, 6, &count);
  std::vector<std::uint8_t> keep(static_cast<std::size_t>(count) + 1, 0);
  int seeds_found = 0;
  for (const auto& p : ventricle_points_mm) {
    const std::ptrdiff_t v = nearest_candidate(csf, p, spec.seed_search_mm);
    if (v < 0) continue;
    ++seeds_found;
    keep[static_cast<std::size_t>(components.voxels[static_cast<std::size_t>(v)])] = 1;
  }
  ThresholdSegmentation out;
  out.labels = LabelImage(g, 0);
  std::size_t n_vent = 0;
  for (std::size_t v = 0; v < brain.voxels.size(); ++v) {
    if (!brain.voxels[v]) continue;
    const bool vent = components.voxels[v] > 0 && keep[static_cast<std::size_t>(components.voxels[v])];
    out.labels.voxels[v] = vent ? spec.ventricle_label : spec.brain_label;
    n_vent += vent;
  }
  const double voxel_ml = std::abs(g.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
  out.description = {{"contrast", contrast_name(spec.contrast)},
                     {"thresholds", {low, high}},
                     {"brain_ml", volume_ml(brain)},
                     {"ventricles_ml", n_vent * voxel_ml},
                     {"ventricle_seeds", {{"given", ventricle_points_mm.size()}, {"found", seeds_found}}}};
  return out;
}

}  // namespace brainshift
