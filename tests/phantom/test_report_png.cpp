// The report picture: a valid PNG of the expected size, contours drawn in the
// structure colours, and a difference row that is black where the images agree.
#include <gtest/gtest.h>
#include <png.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "core/errors.h"
#include "phantom/report_png.h"

namespace brainshift {
namespace {

struct Decoded {
  int width = 0, height = 0;
  std::vector<std::uint8_t> rgb;
  std::array<std::uint8_t, 3> at(int x, int y) const {
    const std::size_t o = 3 * (static_cast<std::size_t>(y) * width + x);
    return {rgb[o], rgb[o + 1], rgb[o + 2]};
  }
};

Decoded decode(const std::filesystem::path& path) {
  Decoded d;
  png_image image{};
  image.version = PNG_IMAGE_VERSION;
  if (!png_image_begin_read_from_file(&image, path.c_str())) return d;
  image.format = PNG_FORMAT_RGB;
  d.width = static_cast<int>(image.width);
  d.height = static_cast<int>(image.height);
  d.rgb.resize(PNG_IMAGE_SIZE(image));
  if (!png_image_finish_read(&image, nullptr, d.rgb.data(), 0, nullptr)) d.width = d.height = 0;
  return d;
}

struct Scene {
  ImageF intraop, affine, nonrigid;
  LabelImage labels;
};

// Anisotropic 1 x 1 x 2.5 mm grid: a ball brain with a tumour inside; the
// "affine" result is shifted by 4 mm, the "non-rigid" one is perfect.
Scene make_scene() {
  Grid3 g;
  g.dims = {80, 80, 32};
  g.world_from_voxel = Eigen::Vector4d(1.0, 1.0, 2.5, 1).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-40, -40, -40);
  Scene s{ImageF(g, 0.f), ImageF(g, 0.f), ImageF(g, 0.f), LabelImage(g, 0)};
  for (int k = 0; k < 32; ++k)
    for (int j = 0; j < 80; ++j)
      for (int i = 0; i < 80; ++i) {
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        auto brain = [](const Eigen::Vector3d& p) {
          return p.norm() < 30 ? 100.f + 30.f * static_cast<float>(std::sin(p.x() / 4)) : 0.f;
        };
        s.intraop.at(i, j, k) = brain(x);
        s.nonrigid.at(i, j, k) = brain(x);
        s.affine.at(i, j, k) = brain(x + Eigen::Vector3d(4, 0, 0));
        s.labels.at(i, j, k) = x.norm() < 30 ? ((x - Eigen::Vector3d(5, 5, 0)).norm() < 8 ? 4 : 1) : 0;
      }
  return s;
}

TEST(ReportPng, WritesAValidPngOfTheExpectedSize) {
  const Scene s = make_scene();
  const auto path = std::filesystem::temp_directory_path() / "brainshift_test_report.png";
  const ReportImageSize size = write_report_png(path, {&s.intraop, &s.affine, &s.nonrigid, &s.labels});
  // Panels cover the 80 mm box at the 1 mm smallest spacing: 3 x 80 + 4 gaps of 4.
  EXPECT_EQ(size.width, 3 * 80 + 16);
  EXPECT_EQ(size.height, 3 * 80 + 16);
  const Decoded d = decode(path);
  ASSERT_EQ(d.width, size.width);
  ASSERT_EQ(d.height, size.height);

  // Row 1 contains the brain (green) and tumour (yellow) contour colours.
  int green = 0, yellow = 0;
  for (int y = 4; y < 84; ++y)
    for (int x = 0; x < d.width; ++x) {
      const auto c = d.at(x, y);
      green += c == std::array<std::uint8_t, 3>{40, 220, 60};
      yellow += c == std::array<std::uint8_t, 3>{255, 230, 0};
    }
  EXPECT_GT(green, 100);
  EXPECT_GT(yellow, 20);
  // Row 2 (affine, misaligned) is brighter than row 3 (perfect: black).
  long row2 = 0, row3 = 0;
  for (int y = 0; y < 80; ++y)
    for (int x = 0; x < d.width; ++x) {
      row2 += d.at(x, 88 + y)[0];
      row3 += d.at(x, 172 + y)[0];
    }
  EXPECT_GT(row2, 1000);
  EXPECT_EQ(row3, 0);
  std::filesystem::remove(path);
}

TEST(ReportPng, PixelSizeOptionAndBytesAgree) {
  const Scene s = make_scene();
  ReportOptions opt;
  opt.pixel_mm = 2.0;
  opt.centre_mm = Eigen::Vector3d(0, 0, 0);
  ReportImageSize size;
  const std::string bytes = report_png_bytes({&s.intraop, &s.affine, &s.nonrigid, &s.labels}, opt, &size);
  EXPECT_EQ(size.width, 3 * 40 + 16);
  ASSERT_GT(bytes.size(), 8u);
  EXPECT_EQ(png_sig_cmp(reinterpret_cast<png_const_bytep>(bytes.data()), 0, 8), 0);
}

TEST(ReportPng, RejectsMissingInputsAndUnwritablePaths) {
  const Scene s = make_scene();
  EXPECT_THROW(report_png_bytes({&s.intraop, nullptr, &s.nonrigid, &s.labels}), InputError);
  EXPECT_THROW(write_report_png("/nonexistent-dir/x.png", {&s.intraop, &s.affine, &s.nonrigid, &s.labels}),
               InputError);
}

}  // namespace
}  // namespace brainshift
