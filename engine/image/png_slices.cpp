#include "image/png_slices.h"

#include <png.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <memory>
#include <vector>

#include "core/errors.h"

namespace brainshift {
namespace {

std::array<float, 2> window_1_99(const ImageF& image) {
  std::vector<float> v = image.voxels;
  if (v.empty()) return {0.f, 1.f};
  const auto at = [&](double q) {
    auto it = v.begin() + static_cast<std::ptrdiff_t>(q * (v.size() - 1));
    std::nth_element(v.begin(), it, v.end());
    return *it;
  };
  const float lo = at(0.01), hi = at(0.99);
  return {lo, hi > lo ? hi : lo + 1.f};
}

std::array<std::uint8_t, 3> label_colour(std::uint16_t label) {
  switch (label) {
    case 1: return {0, 200, 0};
    case 2: return {40, 90, 255};
    case 3: return {255, 30, 30};
    case 4: return {255, 220, 0};
    default: return {255, 0, 255};
  }
}

void save_rgb(const std::filesystem::path& path, int width, int height, const std::vector<std::uint8_t>& rgb) {
  std::unique_ptr<FILE, int (*)(FILE*)> fp(std::fopen(path.c_str(), "wb"), &std::fclose);
  if (!fp) throw InputError(path.string() + ": cannot open for writing");
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  if (!info) {
    png_destroy_write_struct(&png, nullptr);
    throw ComputeError("libpng initialisation failed");
  }
  if (setjmp(png_jmpbuf(png))) {  // libpng reports errors by longjmp
    png_destroy_write_struct(&png, &info);
    throw InputError(path.string() + ": libpng failed while writing");
  }
  png_init_io(png, fp.get());
  png_set_IHDR(png, info, width, height, 8, PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  for (int r = 0; r < height; ++r)
    png_write_row(png, const_cast<png_bytep>(rgb.data() + static_cast<std::size_t>(r) * width * 3));
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
}

}  // namespace

void write_png_slice(const std::filesystem::path& path, const ImageF& image, const LabelImage* labels,
                     SliceAxis axis, int index) {
  const Grid3& g = image.grid;
  if (labels && labels->grid.dims != g.dims)
    throw InputError(path.string() + ": label overlay grid differs from the image grid");
  const int a = static_cast<int>(axis);
  if (index < 0 || index >= g.dims[a])
    throw InputError(path.string() + ": slice index " + std::to_string(index) + " outside 0.." +
                     std::to_string(g.dims[a] - 1));
  // Displayed axes: the two remaining voxel axes, lower one horizontal.
  const int u = a == 0 ? 1 : 0, w = a == 2 ? 1 : 2;
  const int width = g.dims[u], height = g.dims[w];
  const auto [lo, hi] = window_1_99(image);
  std::vector<std::uint8_t> rgb(static_cast<std::size_t>(width) * height * 3);
  for (int r = 0; r < height; ++r)
    for (int c = 0; c < width; ++c) {
      int p[3];
      p[a] = index;
      p[u] = c;
      p[w] = height - 1 - r;  // second axis increases upwards
      const std::size_t v = g.index(p[0], p[1], p[2]);
      const float t = std::clamp((image.voxels[v] - lo) / (hi - lo), 0.f, 1.f);
      std::array<float, 3> px{255 * t, 255 * t, 255 * t};
      if (labels && labels->voxels[v] != 0) {
        const auto col = label_colour(labels->voxels[v]);
        for (int ch = 0; ch < 3; ++ch) px[ch] = 0.6f * px[ch] + 0.4f * col[ch];
      }
      for (int ch = 0; ch < 3; ++ch)
        rgb[(static_cast<std::size_t>(r) * width + c) * 3 + ch] = static_cast<std::uint8_t>(px[ch] + 0.5f);
    }
  save_rgb(path, width, height, rgb);
}

}  // namespace brainshift
