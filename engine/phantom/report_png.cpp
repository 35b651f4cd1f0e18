#include "phantom/report_png.h"

#include <png.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <fstream>
#include <vector>

#include "core/errors.h"
#include "image/resample.h"

namespace brainshift {
namespace {

using Rgb = std::array<std::uint8_t, 3>;

struct Canvas {
  int width = 0, height = 0;
  std::vector<std::uint8_t> rgb;
  void set(int x, int y, const Rgb& c) {
    if (x < 0 || y < 0 || x >= width || y >= height) return;
    std::copy(c.begin(), c.end(), rgb.begin() + 3 * (static_cast<std::size_t>(y) * width + x));
  }
};

// A view: the in-plane world axes (right, up) of one anatomical plane.
struct View {
  Eigen::Vector3d right, up;
};
const std::array<View, 3> kViews{{
    {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY()},  // axial
    {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitZ()},  // coronal
    {Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitZ()},  // sagittal
}};

Eigen::Vector3d default_centre(const LabelImage& labels, std::uint16_t tumor) {
  Eigen::Vector3d sum_t = Eigen::Vector3d::Zero(), sum_all = Eigen::Vector3d::Zero();
  std::size_t n_t = 0, n_all = 0;
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        const auto l = labels.at(i, j, k);
        if (l == 0) continue;
        sum_all += Eigen::Vector3d(i, j, k);
        ++n_all;
        if (l == tumor) {
          sum_t += Eigen::Vector3d(i, j, k);
          ++n_t;
        }
      }
  const Eigen::Vector3d v = n_t ? Eigen::Vector3d(sum_t / static_cast<double>(n_t))
                                : n_all ? Eigen::Vector3d(sum_all / static_cast<double>(n_all))
                                        : Eigen::Vector3d((d[0] - 1) / 2.0, (d[1] - 1) / 2.0, (d[2] - 1) / 2.0);
  return labels.grid.world_mm(v.x(), v.y(), v.z());
}

// 99th percentile of the image inside the labelled region (whole image when
// the region is empty); used to put scans on a common intensity scale.
double brain_p99(const ImageF& image, const LabelImage& labels) {
  std::vector<float> values;
  const bool same = image.grid.same_geometry(labels.grid);
  const auto& d = image.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        const std::uint16_t l =
            same ? labels.at(i, j, k) : sample_nearest(labels, image.grid.world_mm(i, j, k), 0);
        if (l) values.push_back(image.at(i, j, k));
      }
  if (values.empty()) values = image.voxels;
  const std::size_t n = static_cast<std::size_t>(0.99 * (values.size() - 1));
  std::nth_element(values.begin(), values.begin() + n, values.end());
  return values[n] > 0 ? values[n] : 1.0;
}

Rgb structure_colour(std::uint16_t label) {
  switch (label) {
    case 1: return {40, 220, 60};
    case 2: return {0, 200, 255};
    case 3: return {255, 40, 40};
    case 4: return {255, 230, 0};
    default: return {255, 0, 255};
  }
}

std::uint8_t grey(double v) { return static_cast<std::uint8_t>(std::clamp(v, 0.0, 1.0) * 255.0 + 0.5); }

class ReportPainter {
 public:
  ReportPainter(const ReportInputs& in, const ReportOptions& opt) : in_(in), opt_(opt) {
    const Grid3& g = in.intraop->grid;
    pixel_mm_ = opt.pixel_mm > 0 ? opt.pixel_mm : g.spacing_mm().minCoeff();
    // Panels cover the intraop grid's world bounding box on every axis.
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3d w = g.world_mm((c & 1) ? g.dims[0] - 0.5 : -0.5, (c & 2) ? g.dims[1] - 0.5 : -0.5,
                                           (c & 4) ? g.dims[2] - 0.5 : -0.5);
      lo = lo.cwiseMin(w);
      hi = hi.cwiseMax(w);
    }
    box_centre_ = (lo + hi) / 2;
    panel_ = static_cast<int>(std::ceil((hi - lo).maxCoeff() / pixel_mm_));
    centre_ = opt.centre_mm ? *opt.centre_mm : default_centre(*in.warped_labels, opt.tumor_label);
    scale_intraop_ = brain_p99(*in.intraop, *in.warped_labels);
    scale_affine_ = brain_p99(*in.warped_preop_affine, *in.warped_labels);
    scale_nonrigid_ = brain_p99(*in.warped_preop_nonrigid, *in.warped_labels);
    canvas_.width = 3 * panel_ + 4 * kGap;
    canvas_.height = 3 * panel_ + 4 * kGap;
    canvas_.rgb.assign(3 * static_cast<std::size_t>(canvas_.width) * canvas_.height, 0);
  }

  Canvas paint() {
    for (int v = 0; v < 3; ++v) {
      paint_anatomy(v, kGap + v * (panel_ + kGap), kGap);
      paint_difference(v, *in_.warped_preop_affine, scale_affine_, kGap + v * (panel_ + kGap), 2 * kGap + panel_);
      paint_difference(v, *in_.warped_preop_nonrigid, scale_nonrigid_, kGap + v * (panel_ + kGap),
                       3 * kGap + 2 * panel_);
    }
    return std::move(canvas_);
  }

 private:
  static constexpr int kGap = 4;

  // World point of panel pixel (x, y) (y downwards) of view v. The slice
  // passes through centre_; in-plane it is centred on the grid's box.
  Eigen::Vector3d world(int v, int x, int y) const {
    const View& view = kViews[v];
    const Eigen::Vector3d normal = view.right.cross(view.up);
    Eigen::Vector3d p = box_centre_ + (centre_ - box_centre_).dot(normal) * normal;
    p += ((x + 0.5) - panel_ / 2.0) * pixel_mm_ * view.right;
    p += (panel_ / 2.0 - (y + 0.5)) * pixel_mm_ * view.up;
    return p;
  }

  void paint_anatomy(int v, int x0, int y0) {
    std::vector<std::uint16_t> labels(static_cast<std::size_t>(panel_) * panel_);
    for (int y = 0; y < panel_; ++y)
      for (int x = 0; x < panel_; ++x) {
        const Eigen::Vector3d w = world(v, x, y);
        const double value = sample_linear(*in_.intraop, w, 0.f) / scale_intraop_;
        const std::uint8_t g = grey(value);
        canvas_.set(x0 + x, y0 + y, {g, g, g});
        labels[static_cast<std::size_t>(y) * panel_ + x] = sample_nearest(*in_.warped_labels, w, 0);
      }
    // Contours of each structure: brain = any non-zero label; others by value.
    auto draw = [&](auto&& inside, const Rgb& colour) {
      for (int y = 0; y < panel_; ++y)
        for (int x = 0; x < panel_; ++x) {
          if (!inside(labels[static_cast<std::size_t>(y) * panel_ + x])) continue;
          const bool edge = x == 0 || y == 0 || x == panel_ - 1 || y == panel_ - 1 ||
                            !inside(labels[static_cast<std::size_t>(y) * panel_ + x - 1]) ||
                            !inside(labels[static_cast<std::size_t>(y) * panel_ + x + 1]) ||
                            !inside(labels[static_cast<std::size_t>(y - 1) * panel_ + x]) ||
                            !inside(labels[static_cast<std::size_t>(y + 1) * panel_ + x]);
          if (edge) canvas_.set(x0 + x, y0 + y, colour);
        }
    };
    draw([](std::uint16_t l) { return l != 0; }, structure_colour(1));
    std::vector<std::uint16_t> present(labels.begin(), labels.end());
    std::sort(present.begin(), present.end());
    present.erase(std::unique(present.begin(), present.end()), present.end());
    for (std::uint16_t l : present)
      if (l > 1) draw([l](std::uint16_t q) { return q == l; }, structure_colour(l));
  }

  void paint_difference(int v, const ImageF& warped, double scale, int x0, int y0) {
    for (int y = 0; y < panel_; ++y)
      for (int x = 0; x < panel_; ++x) {
        const Eigen::Vector3d w = world(v, x, y);
        const float outside = -1e30f;
        const float a = sample_linear(*in_.intraop, w, outside);
        if (a == outside) continue;  // outside the intraop scan: black
        const double diff = std::abs(a / scale_intraop_ - sample_linear(warped, w, 0.f) / scale);
        const std::uint8_t g = grey(diff / opt_.difference_window);
        canvas_.set(x0 + x, y0 + y, {g, g, g});
      }
  }

  const ReportInputs& in_;
  const ReportOptions& opt_;
  double pixel_mm_ = 1;
  int panel_ = 0;
  Eigen::Vector3d box_centre_, centre_;
  double scale_intraop_ = 1, scale_affine_ = 1, scale_nonrigid_ = 1;
  Canvas canvas_;
};

void append_to_string(png_structp png, png_bytep data, png_size_t length) {
  static_cast<std::string*>(png_get_io_ptr(png))->append(reinterpret_cast<const char*>(data), length);
}

std::string encode_png(const Canvas& c) {
  std::string out;
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  if (!png || !info) {
    png_destroy_write_struct(&png, &info);
    throw ComputeError("report_png: libpng could not be initialised");
  }
  if (setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    throw ComputeError("report_png: libpng failed while encoding");
  }
  png_set_write_fn(png, &out, append_to_string, nullptr);
  png_set_IHDR(png, info, c.width, c.height, 8, PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  for (int y = 0; y < c.height; ++y)
    png_write_row(png, const_cast<png_bytep>(c.rgb.data() + 3 * static_cast<std::size_t>(y) * c.width));
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  return out;
}

void check_inputs(const ReportInputs& in) {
  if (!in.intraop || !in.warped_preop_affine || !in.warped_preop_nonrigid || !in.warped_labels)
    throw InputError("report_png: intraop, warped_preop_affine, warped_preop_nonrigid and warped_labels are required");
  for (const Grid3* g : {&in.intraop->grid, &in.warped_preop_affine->grid, &in.warped_preop_nonrigid->grid,
                         &in.warped_labels->grid})
    if (g->voxel_count() == 0) throw InputError("report_png: an input image is empty");
}

}  // namespace

std::string report_png_bytes(const ReportInputs& inputs, const ReportOptions& options, ReportImageSize* size) {
  check_inputs(inputs);
  if (options.pixel_mm < 0 || !(options.difference_window > 0))
    throw InputError("report_png: pixel_mm must be >= 0 and difference_window > 0");
  ReportPainter painter(inputs, options);
  const Canvas canvas = painter.paint();
  if (size) *size = {canvas.width, canvas.height};
  return encode_png(canvas);
}

ReportImageSize write_report_png(const std::filesystem::path& path, const ReportInputs& inputs,
                                 const ReportOptions& options) {
  ReportImageSize size;
  const std::string bytes = report_png_bytes(inputs, options, &size);
  std::ofstream f(path, std::ios::binary);
  f.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (!f) throw InputError(path.string() + ": cannot write the report PNG");
  return size;
}

}  // namespace brainshift
