#include "report/report_panels.h"

#include <algorithm>
#include <cmath>

#include "image/resample.h"

namespace brainshift::report_detail {
namespace {

Eigen::Vector3d default_centre(const LabelImage& labels, std::uint16_t centre_label) {
  Eigen::Vector3d sum_c = Eigen::Vector3d::Zero(), sum_all = Eigen::Vector3d::Zero();
  std::size_t n_c = 0, n_all = 0;
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        const auto l = labels.at(i, j, k);
        if (l == 0) continue;
        sum_all += Eigen::Vector3d(i, j, k);
        ++n_all;
        if (centre_label != 0 && l == centre_label) {
          sum_c += Eigen::Vector3d(i, j, k);
          ++n_c;
        }
      }
  const Eigen::Vector3d v = n_c     ? Eigen::Vector3d(sum_c / static_cast<double>(n_c))
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

// 99th percentile of the map where it claims an answer (> 0), rounded up to
// 0.5 mm so the colour bar reads in round numbers.
double band_scale_mm(const ImageF& band) {
  std::vector<float> values;
  for (float v : band.voxels)
    if (v > 0) values.push_back(v);
  if (values.empty()) return 1.0;
  const std::size_t n = static_cast<std::size_t>(0.99 * (values.size() - 1));
  std::nth_element(values.begin(), values.begin() + n, values.end());
  return std::max(0.5, std::ceil(2.0 * values[n]) / 2.0);
}

std::uint8_t grey(double v) { return static_cast<std::uint8_t>(std::clamp(v, 0.0, 1.0) * 255.0 + 0.5); }

class PanelPainter {
 public:
  PanelPainter(const ReportInputs& in, const ReportOptions& opt) : in_(in), opt_(opt) {
    const Grid3& g = in.intraop->grid;
    // Panels cover the intraop grid's world bounding box on every axis.
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3d w = g.world_mm((c & 1) ? g.dims[0] - 0.5 : -0.5, (c & 2) ? g.dims[1] - 0.5 : -0.5,
                                           (c & 4) ? g.dims[2] - 0.5 : -0.5);
      lo = lo.cwiseMin(w);
      hi = hi.cwiseMax(w);
    }
    box_centre_ = (lo + hi) / 2;
    const double extent_mm = (hi - lo).maxCoeff();
    // At least kMinPanel pixels, so that the markers, the scale bar and the
    // contours stay legible on a small field of view.
    out_.pixel_mm = opt.pixel_mm > 0 ? opt.pixel_mm : std::min(g.spacing_mm().minCoeff(), extent_mm / kMinPanel);
    out_.size = static_cast<int>(std::ceil(extent_mm / out_.pixel_mm - 1e-9));
    out_.centre_mm = opt.centre_mm ? *opt.centre_mm : default_centre(*in.warped_labels, opt.centre_label);
    scale_intraop_ = brain_p99(*in.intraop, *in.warped_labels);
    scale_affine_ = brain_p99(*in.warped_preop_affine, *in.warped_labels);
    scale_nonrigid_ = brain_p99(*in.warped_preop_nonrigid, *in.warped_labels);
  }

  Panels paint() {
    for (int v = 0; v < 3; ++v) {
      out_.rows[0][v] = anatomy(v);
      out_.rows[1][v] = difference(v, *in_.warped_preop_affine, scale_affine_);
      out_.rows[2][v] = difference(v, *in_.warped_preop_nonrigid, scale_nonrigid_);
    }
    if (in_.uncertainty_mm && !in_.uncertainty_mm->voxels.empty()) {
      out_.uncertainty_max_mm = band_scale_mm(*in_.uncertainty_mm);
      for (int v = 0; v < 3; ++v) out_.uncertainty[v] = uncertainty(v);
    }
    return std::move(out_);
  }

 private:
  static constexpr int kMinPanel = 240;

  Raster blank() const {
    Raster r;
    r.size = out_.size;
    r.rgb.assign(3 * static_cast<std::size_t>(r.size) * r.size, 0);
    return r;
  }
  static void set(Raster& r, int x, int y, const LabelColour& c) {
    std::copy(c.begin(), c.end(), r.rgb.begin() + 3 * (static_cast<std::size_t>(y) * r.size + x));
  }

  // World point of panel pixel (x, y) (y downwards) of view v. The slice
  // passes through the centre; in-plane it is centred on the grid's box.
  Eigen::Vector3d world(int v, int x, int y) const {
    const View& view = views()[v];
    const Eigen::Vector3d normal = view.right.cross(view.up);
    Eigen::Vector3d p = box_centre_ + (out_.centre_mm - box_centre_).dot(normal) * normal;
    p += ((x + 0.5) - out_.size / 2.0) * out_.pixel_mm * view.right;
    p += (out_.size / 2.0 - (y + 0.5)) * out_.pixel_mm * view.up;
    return p;
  }

  LabelColour colour_of(std::uint16_t label) const {
    for (const auto& e : in_.legend)
      if (e.value == label) return e.colour;
    return {255, 0, 255};
  }

  Raster anatomy(int v) const {
    Raster r = blank();
    const int n = r.size;
    std::vector<std::uint16_t> labels(static_cast<std::size_t>(n) * n);
    for (int y = 0; y < n; ++y)
      for (int x = 0; x < n; ++x) {
        const Eigen::Vector3d w = world(v, x, y);
        const std::uint8_t g = grey(sample_linear(*in_.intraop, w, 0.f) / scale_intraop_);
        set(r, x, y, {g, g, g});
        labels[static_cast<std::size_t>(y) * n + x] = sample_nearest(*in_.warped_labels, w, 0);
      }
    auto at = [&](int x, int y) { return labels[static_cast<std::size_t>(y) * n + x]; };
    auto draw = [&](auto&& inside, const LabelColour& colour) {
      for (int y = 0; y < n; ++y)
        for (int x = 0; x < n; ++x) {
          if (!inside(at(x, y))) continue;
          const bool edge = x == 0 || y == 0 || x == n - 1 || y == n - 1 || !inside(at(x - 1, y)) ||
                            !inside(at(x + 1, y)) || !inside(at(x, y - 1)) || !inside(at(x, y + 1));
          if (edge) set(r, x, y, colour);
        }
    };
    // The outer surface first (any structure lies inside it), then each inner
    // structure by value, so inner contours stay visible where they touch it.
    draw([](std::uint16_t l) { return l != 0; }, colour_of(in_.outer_label));
    std::vector<std::uint16_t> present(labels.begin(), labels.end());
    std::sort(present.begin(), present.end());
    present.erase(std::unique(present.begin(), present.end()), present.end());
    for (std::uint16_t l : present)
      if (l != 0 && l != in_.outer_label) draw([l](std::uint16_t q) { return q == l; }, colour_of(l));
    if (in_.segmentation) draw_segmentation(r, v);
    return r;
  }

  // Every other pixel of each edge of the segmentation (outline and each
  // inner label), in white: dotted, so it reads apart from the preop contours.
  void draw_segmentation(Raster& r, int v) const {
    const int n = r.size;
    std::vector<std::uint16_t> seg(static_cast<std::size_t>(n) * n);
    for (int y = 0; y < n; ++y)
      for (int x = 0; x < n; ++x) seg[static_cast<std::size_t>(y) * n + x] = sample_nearest(*in_.segmentation, world(v, x, y), 0);
    auto at = [&](int x, int y) { return seg[static_cast<std::size_t>(y) * n + x]; };
    for (int y = 1; y < n - 1; ++y)
      for (int x = 1; x < n - 1; ++x) {
        const std::uint16_t l = at(x, y);
        const bool edge = (l != 0) && (at(x - 1, y) != l || at(x + 1, y) != l || at(x, y - 1) != l || at(x, y + 1) != l);
        if (edge && (x + y) % 3 != 0) set(r, x, y, {255, 255, 255});
      }
  }

  Raster difference(int v, const ImageF& warped, double scale) const {
    Raster r = blank();
    for (int y = 0; y < r.size; ++y)
      for (int x = 0; x < r.size; ++x) {
        const Eigen::Vector3d w = world(v, x, y);
        const float outside = -1e30f;
        const float a = sample_linear(*in_.intraop, w, outside);
        if (a == outside) continue;  // outside the intraop scan: black
        const double diff = std::abs(a / scale_intraop_ - sample_linear(warped, w, 0.f) / scale);
        const std::uint8_t g = grey(diff / opt_.difference_window);
        set(r, x, y, {g, g, g});
      }
    return r;
  }

  // The band in colour (60 % over the intraop grey) where the map claims an
  // answer; the grey image alone elsewhere.
  Raster uncertainty(int v) const {
    Raster r = blank();
    for (int y = 0; y < r.size; ++y)
      for (int x = 0; x < r.size; ++x) {
        const Eigen::Vector3d w = world(v, x, y);
        const double g = grey(sample_linear(*in_.intraop, w, 0.f) / scale_intraop_);
        const float band = sample_linear(*in_.uncertainty_mm, w, 0.f);
        if (band <= 0) {
          const auto gg = static_cast<std::uint8_t>(g);
          set(r, x, y, {gg, gg, gg});
          continue;
        }
        const LabelColour c = uncertainty_colour(band / out_.uncertainty_max_mm);
        LabelColour mixed;
        for (int k = 0; k < 3; ++k) mixed[k] = static_cast<std::uint8_t>(std::lround(0.4 * g + 0.6 * c[k]));
        set(r, x, y, mixed);
      }
    return r;
  }

  const ReportInputs& in_;
  const ReportOptions& opt_;
  Panels out_;
  Eigen::Vector3d box_centre_;
  double scale_intraop_ = 1, scale_affine_ = 1, scale_nonrigid_ = 1;
};

}  // namespace

LabelColour uncertainty_colour(double t) {
  t = std::clamp(t, 0.0, 1.0);
  const auto mix = [](double a, double b, double f) { return static_cast<std::uint8_t>(std::lround(a + (b - a) * f)); };
  if (t < 0.5) return {mix(40, 250, 2 * t), mix(70, 220, 2 * t), mix(220, 40, 2 * t)};
  return {mix(250, 220, 2 * t - 1), mix(220, 30, 2 * t - 1), mix(40, 30, 2 * t - 1)};
}

const std::array<View, 3>& views() {
  // Neurological convention: RAS +x (patient's right) to the screen's right.
  static const std::array<View, 3> v{{
      {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY()},  // axial: R right, A up
      {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitZ()},  // coronal: R right, S up
      {Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitZ()},  // sagittal: A right, S up
  }};
  return v;
}

Panels paint_panels(const ReportInputs& inputs, const ReportOptions& options) {
  return PanelPainter(inputs, options).paint();
}

}  // namespace brainshift::report_detail
