#include "image/intensity_offset.h"

#include <algorithm>
#include <vector>

namespace brainshift {

bool has_negative_intensities(const ImageF& image) {
  return std::any_of(image.voxels.begin(), image.voxels.end(), [](float x) { return x < 0.f; });
}

double lift_negative_intensities(ImageF& image) {
  auto& v = image.voxels;
  if (!has_negative_intensities(image)) return 0.0;
  // Every 7th voxel: a percentile of millions of values needs no more.
  constexpr std::size_t kStride = 7;
  std::vector<float> sample;
  sample.reserve(v.size() / kStride + 1);
  for (std::size_t i = 0; i < v.size(); i += kStride) sample.push_back(v[i]);
  const auto at = sample.begin() + static_cast<std::ptrdiff_t>(kIntensityFloorPercentile * static_cast<double>(sample.size() - 1));
  std::nth_element(sample.begin(), at, sample.end());
  const float floor = std::min(*at, 0.f);
  for (float& x : v) x = std::max(x - floor, 0.f);
  return -static_cast<double>(floor);
}

}  // namespace brainshift
