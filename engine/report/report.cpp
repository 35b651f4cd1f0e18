#include "report/report.h"

#include <cairo.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>

#include "core/errors.h"
#include "report/report_panels.h"

namespace brainshift {
namespace {

using report_detail::Panels;
using report_detail::Raster;

constexpr int kMargin = 14, kGap = 6, kRowLabelWidth = 150, kMinWidth = 940;
constexpr const char* kFont = "DejaVu Sans";  // fonts-dejavu-core; fontconfig substitutes if absent
const LabelColour kBackground{22, 22, 28}, kText{235, 235, 235}, kDim{170, 170, 180};
// White text reads on all four; amber dark enough for it.
const LabelColour kNonrigidBand{30, 110, 50}, kCautionBand{165, 95, 0}, kFallbackBand{170, 30, 30},
    kNeutralBand{60, 70, 90};

struct Surface {
  explicit Surface(int width, int height)
      : surface(cairo_image_surface_create(CAIRO_FORMAT_RGB24, width, height), cairo_surface_destroy),
        cr(cairo_create(surface.get()), cairo_destroy) {
    if (cairo_surface_status(surface.get()) != CAIRO_STATUS_SUCCESS || cairo_status(cr.get()) != CAIRO_STATUS_SUCCESS)
      throw ComputeError("report: Cairo could not make a " + std::to_string(width) + " x " + std::to_string(height) +
                         " picture");
  }
  std::unique_ptr<cairo_surface_t, decltype(&cairo_surface_destroy)> surface;
  std::unique_ptr<cairo_t, decltype(&cairo_destroy)> cr;
};

void set_colour(cairo_t* cr, const LabelColour& c) {
  cairo_set_source_rgb(cr, c[0] / 255.0, c[1] / 255.0, c[2] / 255.0);
}

void font(cairo_t* cr, double size, bool bold) {
  cairo_select_font_face(cr, kFont, CAIRO_FONT_SLANT_NORMAL, bold ? CAIRO_FONT_WEIGHT_BOLD : CAIRO_FONT_WEIGHT_NORMAL);
  cairo_set_font_size(cr, size);
}

double text_width(cairo_t* cr, const std::string& s) {
  cairo_text_extents_t e;
  cairo_text_extents(cr, s.c_str(), &e);
  return e.x_advance;
}

// y is the baseline.
void text(cairo_t* cr, double x, double y, const std::string& s, const LabelColour& c) {
  set_colour(cr, c);
  cairo_move_to(cr, x, y);
  cairo_show_text(cr, s.c_str());
}

// Words of s in lines no wider than width (current font); at most max_lines,
// the last ending in "..." when the text did not fit.
std::vector<std::string> wrap(cairo_t* cr, const std::string& s, double width, std::size_t max_lines) {
  std::vector<std::string> lines{""};
  std::size_t at = 0;
  while (at < s.size()) {
    const std::size_t end = std::min(s.find(' ', at), s.size());
    const std::string word = s.substr(at, end - at);
    at = end + 1;
    const std::string joined = lines.back().empty() ? word : lines.back() + " " + word;
    if (text_width(cr, joined) <= width || lines.back().empty()) {
      lines.back() = joined;
      continue;
    }
    if (lines.size() == max_lines) {
      lines.back() += " ...";
      return lines;
    }
    lines.push_back(word);
  }
  return lines;
}

std::string number(const std::optional<double>& v, const char* format) {
  if (!v) return "n/a";
  char buffer[64];
  std::snprintf(buffer, sizeof buffer, format, *v);
  return buffer;
}

void paint_raster(cairo_t* cr, const Raster& r, int x0, int y0) {
  Surface tile(r.size, r.size);
  cairo_surface_t* s = tile.surface.get();
  cairo_surface_flush(s);
  unsigned char* data = cairo_image_surface_get_data(s);
  const int stride = cairo_image_surface_get_stride(s);
  for (int y = 0; y < r.size; ++y) {
    auto* row = reinterpret_cast<std::uint32_t*>(data + static_cast<std::size_t>(y) * stride);
    for (int x = 0; x < r.size; ++x) {
      const std::uint8_t* p = &r.rgb[3 * (static_cast<std::size_t>(y) * r.size + x)];
      row[x] = (std::uint32_t{p[0]} << 16) | (std::uint32_t{p[1]} << 8) | p[2];
    }
  }
  cairo_surface_mark_dirty(s);
  cairo_set_source_surface(cr, s, x0, y0);
  cairo_pattern_set_filter(cairo_get_source(cr), CAIRO_FILTER_NEAREST);
  cairo_rectangle(cr, x0, y0, r.size, r.size);
  cairo_fill(cr);
}

// A letter readable on any grey: dark outline, light fill.
void marker(cairo_t* cr, double x, double y, const std::string& s) {
  cairo_move_to(cr, x, y);
  cairo_text_path(cr, s.c_str());
  cairo_set_source_rgb(cr, 0, 0, 0);
  cairo_set_line_width(cr, 3);
  cairo_stroke_preserve(cr);
  cairo_set_source_rgb(cr, 1, 0.95, 0.4);
  cairo_fill(cr);
}

// Screen left, right, top, bottom of each view in neurological convention.
const std::array<std::array<const char*, 4>, 3> kMarkers{{
    {"L", "R", "A", "P"}, {"L", "R", "S", "I"}, {"P", "A", "S", "I"}}};

void orientation_markers(cairo_t* cr, int view, const ReportRect& p) {
  font(cr, 13, true);
  const auto& m = kMarkers[view];
  const double cx = p.x + p.width / 2.0, cy = p.y + p.height / 2.0;
  marker(cr, p.x + 4, cy + 5, m[0]);
  marker(cr, p.x + p.width - 4 - text_width(cr, m[1]), cy + 5, m[1]);
  marker(cr, cx - text_width(cr, m[2]) / 2, p.y + 15, m[2]);
  marker(cr, cx - text_width(cr, m[3]) / 2, p.y + p.height - 5, m[3]);
}

ReportRect scale_bar(cairo_t* cr, const ReportRect& p, double pixel_mm) {
  const double length = 10.0 / pixel_mm;  // 1 cm
  const ReportRect bar{p.x + 10, p.y + p.height - 12, static_cast<int>(std::lround(length)), 4};
  cairo_rectangle(cr, bar.x - 1, bar.y - 1, bar.width + 2, bar.height + 2);
  cairo_set_source_rgb(cr, 0, 0, 0);
  cairo_fill(cr);
  cairo_rectangle(cr, bar.x, bar.y, bar.width, bar.height);
  cairo_set_source_rgb(cr, 1, 1, 1);
  cairo_fill(cr);
  font(cr, 11, true);
  marker(cr, bar.x, bar.y - 4, "1 cm");
  return bar;
}

class Page {
 public:
  Page(const ReportInputs& in, const Panels& panels, double difference_window)
      : in_(in), panels_(panels), window_(difference_window) {}

  // Draws on cr and returns where everything went (and so the page height).
  ReportLayout draw(cairo_t* cr, int width) {
    ReportLayout L;
    L.width = width;
    L.pixel_mm = panels_.pixel_mm;
    set_colour(cr, kBackground);
    cairo_paint(cr);
    int y = kMargin;
    y = title(cr, L, y);
    y = grid(cr, L, y + 8);
    y = legend(cr, L, y + 14);
    y = numbers_and_notes(cr, L, y + 12);
    L.height = y + kMargin;
    return L;
  }

  int width() const { return std::max(kMinWidth, 2 * kMargin + kRowLabelWidth + 3 * panels_.size + 2 * kGap); }

 private:
  int title(cairo_t* cr, ReportLayout& L, int y) {
    const ReportSummary& s = in_.summary;
    font(cr, 20, true);
    const std::string heading =
        "Brain-shift registration" + (s.scan_id.empty() ? std::string() : "  \xE2\x80\x94  scan " + s.scan_id);
    text(cr, kMargin, y + 20, heading, kText);
    L.title = {kMargin, y, static_cast<int>(std::ceil(text_width(cr, heading))), 26};
    y += 32;
    font(cr, 14, true);
    const std::string result =
        !s.result_text.empty() ? s.result_text
        : s.fallback ? "Result: AFFINE-ONLY FALLBACK (the non-rigid correction was rejected): " +
                         (s.fallback_reason.empty() ? std::string("no reason given") : s.fallback_reason)
        : !s.caution.empty() ? "Result: non-rigid correction. CAUTION: " + s.caution
                   : "Result: non-rigid correction (affine, surface match, elastic model)";
    const auto lines = wrap(cr, result, L.width - 2 * kMargin - 16, 4);
    L.result_band = {kMargin, y, L.width - 2 * kMargin, static_cast<int>(10 + 18 * lines.size())};
    set_colour(cr, !s.result_text.empty() ? kNeutralBand
                   : s.fallback           ? kFallbackBand
                   : !s.caution.empty()   ? kCautionBand
                                          : kNonrigidBand);
    cairo_rectangle(cr, L.result_band.x, L.result_band.y, L.result_band.width, L.result_band.height);
    cairo_fill(cr);
    for (std::size_t i = 0; i < lines.size(); ++i) text(cr, kMargin + 8, y + 19 + 18 * i, lines[i], {255, 255, 255});
    return L.result_band.y + L.result_band.height;
  }

  int grid(cairo_t* cr, ReportLayout& L, int y) {
    const int n = panels_.size, x0 = kMargin + kRowLabelWidth;
    const Eigen::Vector3d& c = panels_.centre_mm;
    const std::array<std::string, 3> names{"Axial", "Coronal", "Sagittal"};
    const std::array<std::string, 3> positions{"z = " + number(c.z(), "%.1f") + " mm",
                                               "y = " + number(c.y(), "%.1f") + " mm",
                                               "x = " + number(c.x(), "%.1f") + " mm"};
    for (int v = 0; v < 3; ++v) {
      const double centre = x0 + v * (n + kGap) + n / 2.0;
      font(cr, 13, true);
      text(cr, centre - text_width(cr, names[v]) / 2, y + 14, names[v], kText);
      font(cr, 12, false);
      text(cr, centre - text_width(cr, positions[v]) / 2, y + 30, positions[v], kDim);
    }
    y += 38;
    // Row 3 is the result: the affine again when the non-rigid step was refused.
    const std::array<std::array<const char*, 3>, 3> row_labels{{
        {"Intraop T1", "with the warped", "preop contours"},
        {"Difference after", "the affine only", "|intraop - preop|"},
        {"Difference after", in_.summary.fallback ? "the result (affine)" : "non-rigid", "|intraop - preop|"}}};
    for (int r = 0; r < 3; ++r) {
      const int ry = y + r * (n + kGap);
      font(cr, 13, true);
      text(cr, kMargin, ry + 20, row_labels[r][0], kText);
      font(cr, 13, false);
      text(cr, kMargin, ry + 38, row_labels[r][1], kText);
      text(cr, kMargin, ry + 56, row_labels[r][2], kDim);
      for (int v = 0; v < 3; ++v) {
        const ReportRect p{x0 + v * (n + kGap), ry, n, n};
        L.panels[r][v] = p;
        paint_raster(cr, panels_.rows[r][v], p.x, p.y);
        orientation_markers(cr, v, p);
        if (r == 0) {
          const ReportRect bar = scale_bar(cr, p, panels_.pixel_mm);
          if (v == 0) L.scale_bar = bar;
        }
      }
    }
    if (panels_.uncertainty[0].size == 0) return y + 3 * n + 2 * kGap;
    const int ry = y + 3 * (n + kGap);
    font(cr, 13, true);
    text(cr, kMargin, ry + 20, "Uncertainty", kText);
    font(cr, 13, false);
    text(cr, kMargin, ry + 38, "95 % band radius", kText);
    text(cr, kMargin, ry + 56, "colour bar below, mm", kDim);
    for (int v = 0; v < 3; ++v) {
      const ReportRect p{x0 + v * (n + kGap), ry, n, n};
      L.uncertainty_panels[v] = p;
      paint_raster(cr, panels_.uncertainty[v], p.x, p.y);
      orientation_markers(cr, v, p);
    }
    return ry + n;
  }

  int legend(cairo_t* cr, ReportLayout& L, int y) {
    font(cr, 13, true);
    text(cr, kMargin, y + 13, "Structures:", kText);
    double x = kMargin + text_width(cr, "Structures:") + 14;
    font(cr, 13, false);
    for (const auto& e : in_.legend) {
      const double w = 14 + 6 + text_width(cr, e.name) + 18;
      if (x + w > L.width - kMargin) {
        x = kMargin + 90;
        y += 20;
      }
      const ReportRect swatch{static_cast<int>(x), y + 1, 14, 14};
      set_colour(cr, e.colour);
      cairo_rectangle(cr, swatch.x, swatch.y, swatch.width, swatch.height);
      cairo_fill(cr);
      L.legend_swatches.push_back(swatch);
      text(cr, x + 20, y + 13, e.name, kText);
      x += w;
    }
    return y + 18;
  }

  int numbers_and_notes(cairo_t* cr, ReportLayout& L, int y) {
    const ReportSummary& s = in_.summary;
    struct Row {
      std::string what, affine, final;
    };
    std::vector<Row> rows;
    for (const auto& o : s.overlaps) rows.push_back({"Dice " + o.structure, number(o.dice_affine, "%.3f"), number(o.dice, "%.3f")});
    for (const auto& o : s.overlaps)
      rows.push_back({"Mean surface distance " + o.structure, number(o.mean_distance_affine_mm, "%.2f mm"),
                      number(o.mean_distance_mm, "%.2f mm")});
    rows.push_back({"Min Jacobian determinant", "", number(s.min_jacobian, "%.3f")});
    // 1 when the whole brain is in view; below half a percent (some 8 ml at
    // a corner of the grid) the row would only add noise.
    if (s.brain_in_view_fraction && *s.brain_in_view_fraction < 0.995)
      rows.push_back({"Preop brain in the field of view", "",
                      number(100.0 * *s.brain_in_view_fraction, "%.0f %%") + " (rest not imaged)"});
    if (s.uncertainty_median_mm)
      // Short enough for the column when the p95 has two digits (a cut field of view).
      rows.push_back({"Uncertainty band, median / p95", "", number(s.uncertainty_median_mm, "%.2f") + " / " +
                                                              number(s.uncertainty_p95_mm, "%.2f mm")});
    rows.push_back({"Worst surface residual", "",
                    number(s.worst_residual_mm, "%.2f mm") +
                        (s.worst_residual_surface.empty() ? "" : " (" + s.worst_residual_surface + ")")});
    const int c1 = kMargin + 250, c2 = kMargin + 350, row_h = 18;
    font(cr, 13, true);
    text(cr, kMargin, y + 13, "Key numbers", kText);
    text(cr, c1, y + 13, "affine only", kDim);
    text(cr, c2, y + 13, s.fallback ? "result (affine)" : "non-rigid", kDim);
    font(cr, 13, false);
    int ty = y + row_h;
    for (const auto& r : rows) {
      text(cr, kMargin, ty + 13, r.what, kText);
      text(cr, c1, ty + 13, r.affine, kText);
      text(cr, c2, ty + 13, r.final, kText);
      ty += row_h;
    }
    L.numbers = {kMargin, y, c2 + 130 - kMargin, ty - y};
    return std::max(ty, notes(cr, L, kMargin + 520, y, L.width - kMargin - (kMargin + 520)));
  }

  // The display convention and how to read the difference rows.
  int notes(cairo_t* cr, ReportLayout& L, int x, int y, int width) {
    font(cr, 12, false);
    const std::vector<std::string> lines{
        "Display: neurological convention, the patient's right on",
        "the image's right (L/R, A/P and S/I marked on each panel).",
        "Rows 2-3: |intraop - warped preop T1|, each normalised by",
        "its 99th percentile in the brain; darker = better aligned.",
        "Slice positions in RAS mm; the bar in row 1 is 1 cm."};
    int ty = y;
    for (const auto& l : lines) {
      text(cr, x, ty + 12, l, kDim);
      ty += 16;
    }
    // The difference window: 0 (black) to difference_window (white).
    const int bar_w = std::min(width - 80, 200), bar_y = ty + 6;
    cairo_pattern_t* g = cairo_pattern_create_linear(x, 0, x + bar_w, 0);
    cairo_pattern_add_color_stop_rgb(g, 0, 0, 0, 0);
    cairo_pattern_add_color_stop_rgb(g, 1, 1, 1, 1);
    cairo_set_source(cr, g);
    cairo_rectangle(cr, x, bar_y, bar_w, 10);
    cairo_fill(cr);
    cairo_pattern_destroy(g);
    text(cr, x, bar_y + 24, "0", kDim);
    const std::string hi = number(window_, "%.2f");
    text(cr, x + bar_w - text_width(cr, hi), bar_y + 24, hi, kDim);
    if (panels_.uncertainty[0].size == 0) return bar_y + 28;
    return uncertainty_bar(cr, L, x, bar_y + 40, bar_w);
  }

  // Row 4's colour scale: 0 mm to uncertainty_max_mm, in steps of pixels.
  int uncertainty_bar(cairo_t* cr, ReportLayout& L, int x, int y, int bar_w) {
    text(cr, x, y + 12, "Row 4: radius (mm) of the 95 % band around each point.", kDim);
    const int bar_y = y + 18;
    for (int i = 0; i < bar_w; ++i) {
      const LabelColour c = report_detail::uncertainty_colour((i + 0.5) / bar_w);
      cairo_set_source_rgb(cr, c[0] / 255.0, c[1] / 255.0, c[2] / 255.0);
      cairo_rectangle(cr, x + i, bar_y, 1, 10);
      cairo_fill(cr);
    }
    L.uncertainty_bar = {x, bar_y, bar_w, 10};
    L.uncertainty_max_mm = panels_.uncertainty_max_mm;
    text(cr, x, bar_y + 24, "0 mm", kDim);
    const std::string hi = number(panels_.uncertainty_max_mm, "%.1f mm");
    text(cr, x + bar_w - text_width(cr, hi), bar_y + 24, hi, kDim);
    return bar_y + 28;
  }

  const ReportInputs& in_;
  const Panels& panels_;
  double window_;
};

cairo_status_t append_to_string(void* closure, const unsigned char* data, unsigned int length) {
  static_cast<std::string*>(closure)->append(reinterpret_cast<const char*>(data), length);
  return CAIRO_STATUS_SUCCESS;
}

void check_inputs(const ReportInputs& in, const ReportOptions& options) {
  if (!in.intraop || !in.warped_preop_affine || !in.warped_preop_nonrigid || !in.warped_labels)
    throw InputError("report: intraop, warped_preop_affine, warped_preop_nonrigid and warped_labels are required");
  for (const Grid3* g : {&in.intraop->grid, &in.warped_preop_affine->grid, &in.warped_preop_nonrigid->grid,
                         &in.warped_labels->grid})
    if (g->voxel_count() == 0) throw InputError("report: an input image is empty");
  if (options.pixel_mm < 0 || !(options.difference_window > 0))
    throw InputError("report: pixel_mm must be >= 0 and difference_window > 0");
}

}  // namespace

std::string report_png_bytes(const ReportInputs& inputs, const ReportOptions& options, ReportLayout* layout) {
  check_inputs(inputs, options);
  const Panels panels = report_detail::paint_panels(inputs, options);
  Page page(inputs, panels, options.difference_window);
  const int width = page.width();
  // The footer's height depends on how the legend wraps: lay out once on a
  // scratch surface, then draw at the final size.
  int height = 0;
  {
    Surface scratch(width, 1);
    height = page.draw(scratch.cr.get(), width).height;
  }
  Surface canvas(width, height);
  const ReportLayout drawn = page.draw(canvas.cr.get(), width);
  cairo_surface_flush(canvas.surface.get());
  std::string png;
  if (cairo_surface_write_to_png_stream(canvas.surface.get(), append_to_string, &png) != CAIRO_STATUS_SUCCESS)
    throw ComputeError("report: Cairo could not encode the PNG");
  if (layout) *layout = drawn;
  return png;
}

ReportLayout write_report_png(const std::filesystem::path& path, const ReportInputs& inputs,
                              const ReportOptions& options) {
  ReportLayout layout;
  const std::string bytes = report_png_bytes(inputs, options, &layout);
  std::ofstream f(path, std::ios::binary);
  f.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (!f) throw InputError(path.string() + ": cannot write the report PNG");
  return layout;
}

}  // namespace brainshift
