#include <gtest/gtest.h>

#include <fstream>
#include <unistd.h>

#include "core/errors.h"
#include "image/png_slices.h"

namespace brainshift {
namespace {

std::uint32_t big_endian_u32(const std::string& s, std::size_t at) {
  return (std::uint32_t(std::uint8_t(s[at])) << 24) | (std::uint32_t(std::uint8_t(s[at + 1])) << 16) |
         (std::uint32_t(std::uint8_t(s[at + 2])) << 8) | std::uint32_t(std::uint8_t(s[at + 3]));
}

TEST(PngSlices, WritesPngWithSliceDimensions) {
  Grid3 g;
  g.dims = {12, 7, 5};
  ImageF img(g, 0.f);
  for (std::size_t i = 0; i < img.voxels.size(); ++i) img.voxels[i] = float(i % 13);
  LabelImage lab(g, 0);
  lab.at(3, 3, 2) = 2;
  const auto path = std::filesystem::temp_directory_path() / ("brainshift_slice_" + std::to_string(::getpid()) + ".png");
  write_png_slice(path, img, &lab, SliceAxis::z, 2);  // axial: x horizontal, y vertical
  std::ifstream in(path, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), {});
  ASSERT_GT(bytes.size(), 33u);
  EXPECT_EQ(bytes.substr(0, 8), std::string("\x89PNG\r\n\x1a\n", 8));
  EXPECT_EQ(big_endian_u32(bytes, 16), 12u);  // IHDR width
  EXPECT_EQ(big_endian_u32(bytes, 20), 7u);   // IHDR height
  write_png_slice(path, img, nullptr, SliceAxis::x, 0);  // sagittal: y by z
  std::ifstream in2(path, std::ios::binary);
  const std::string b2((std::istreambuf_iterator<char>(in2)), {});
  EXPECT_EQ(big_endian_u32(b2, 16), 7u);
  EXPECT_EQ(big_endian_u32(b2, 20), 5u);
  EXPECT_THROW(write_png_slice(path, img, nullptr, SliceAxis::y, 7), InputError);
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace brainshift
