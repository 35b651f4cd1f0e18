// An image shifted below zero on its way (a stored intercept, a z-scored
// export) is lifted back to a magnitude image's range; one without negative
// values is not touched.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "image/intensity_offset.h"

using namespace brainshift;

namespace {

// Half air (Rician-like noise near 5), half tissue (100-200): a head scan's
// field of view.
ImageF magnitude_image() {
  Grid3 g;
  g.dims = {40, 30, 20};
  ImageF im(g, 0.f);
  for (std::size_t i = 0; i < im.voxels.size(); ++i)
    im.voxels[i] = i % 2 ? 100.f + static_cast<float>(i % 101) : 5.f + static_cast<float>((i * 7919) % 9) - 4.f;
  return im;
}

}  // namespace

TEST(IntensityOffset, AnImageShiftedBelowZeroIsLiftedSoThatItsAirIsNearZero) {
  const ImageF magnitude = magnitude_image();
  for (const auto& [scale, offset] : {std::pair{1.0, -1024.0}, {0.01, -0.5}, {20.0, -3000.0}}) {
    SCOPED_TRACE(testing::Message() << "x " << scale << " + " << offset);
    ImageF shifted = magnitude;
    for (float& v : shifted.voxels) v = static_cast<float>(scale * v + offset);
    const double by = lift_negative_intensities(shifted);
    // The air's lowest values (1 here) end at zero: the lift is the offset
    // less the air's floor.
    EXPECT_NEAR(by, -offset - scale * 1.0, 1e-3 * std::abs(offset));
    EXPECT_GE(*std::min_element(shifted.voxels.begin(), shifted.voxels.end()), 0.f);
    for (std::size_t i = 0; i < shifted.voxels.size(); i += 97)
      EXPECT_NEAR(shifted.voxels[i], scale * (magnitude.voxels[i] - 1.0), 1e-3 * std::abs(offset)) << i;
  }
  ImageF untouched = magnitude;
  EXPECT_EQ(lift_negative_intensities(untouched), 0.0);
  EXPECT_EQ(untouched.voxels, magnitude.voxels);
  EXPECT_FALSE(has_negative_intensities(magnitude));
  // A few negative outliers (interpolation's ringing) are clamped, not lifted.
  ImageF ringing = magnitude;
  ringing.voxels[3] = -2.f;
  EXPECT_EQ(lift_negative_intensities(ringing), 0.0);
  EXPECT_EQ(ringing.voxels[3], 0.f);
  EXPECT_EQ(ringing.voxels[4], magnitude.voxels[4]);
}
