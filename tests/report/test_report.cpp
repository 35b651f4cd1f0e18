// report.png: a valid PNG of the layout's size whose title, result band,
// legend, scale bar, key numbers and panels hold what they claim; the
// affine-only fallback is told apart; bad inputs are refused.
#include <cairo.h>
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <memory>

#include "core/errors.h"
#include "report/report.h"

namespace brainshift {
namespace {

using Rgb = std::array<std::uint8_t, 3>;

// Decoded with Cairo's PNG reader: the one the writer pairs with.
struct Decoded {
  int width = 0, height = 0;
  std::vector<Rgb> pixels;
  Rgb at(int x, int y) const { return pixels[static_cast<std::size_t>(y) * width + x]; }
};

cairo_status_t read_from_string(void* closure, unsigned char* data, unsigned int length) {
  auto* s = static_cast<std::pair<const std::string*, std::size_t>*>(closure);
  if (s->second + length > s->first->size()) return CAIRO_STATUS_READ_ERROR;
  std::copy_n(s->first->data() + s->second, length, data);
  s->second += length;
  return CAIRO_STATUS_SUCCESS;
}

Decoded decode(const std::string& png) {
  std::pair<const std::string*, std::size_t> source{&png, 0};
  std::unique_ptr<cairo_surface_t, decltype(&cairo_surface_destroy)> s(
      cairo_image_surface_create_from_png_stream(read_from_string, &source), cairo_surface_destroy);
  Decoded d;
  if (cairo_surface_status(s.get()) != CAIRO_STATUS_SUCCESS) return d;
  d.width = cairo_image_surface_get_width(s.get());
  d.height = cairo_image_surface_get_height(s.get());
  const unsigned char* data = cairo_image_surface_get_data(s.get());
  const int stride = cairo_image_surface_get_stride(s.get());
  for (int y = 0; y < d.height; ++y)
    for (int x = 0; x < d.width; ++x) {
      const std::uint32_t p = reinterpret_cast<const std::uint32_t*>(data + static_cast<std::size_t>(y) * stride)[x];
      d.pixels.push_back({static_cast<std::uint8_t>(p >> 16), static_cast<std::uint8_t>(p >> 8),
                          static_cast<std::uint8_t>(p)});
    }
  return d;
}

std::string read_file(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Pixels of r that differ from the page background: text or drawing there.
int inked(const Decoded& d, const ReportRect& r) {
  const Rgb background = d.at(0, 0);
  int n = 0;
  for (int y = r.y; y < r.y + r.height; ++y)
    for (int x = r.x; x < r.x + r.width; ++x) n += d.at(x, y) != background;
  return n;
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

const Rgb kBrain{40, 220, 60}, kTumour{255, 230, 0}, kVentricles{0, 200, 255};

ReportInputs inputs(const Scene& s) {
  ReportInputs in;
  in.intraop = &s.intraop;
  in.warped_preop_affine = &s.affine;
  in.warped_preop_nonrigid = &s.nonrigid;
  in.warped_labels = &s.labels;
  in.legend = {{1, "brain", kBrain}, {2, "ventricles", kVentricles}, {4, "tumor", kTumour}};
  in.outer_label = 1;
  in.summary.scan_id = "scan-0042";
  in.summary.overlaps = {{"brain", 0.91, 0.98, 1.4, 0.3}};
  in.summary.min_jacobian = 0.62;
  in.summary.worst_residual_mm = 1.7;
  in.summary.worst_residual_surface = "brain";
  return in;
}

TEST(Report, PngDecodesToTheLayoutAndEveryRegionHoldsItsContent) {
  const Scene s = make_scene();
  const auto path = std::filesystem::temp_directory_path() / "brainshift_test_report.png";
  const ReportLayout L = write_report_png(path, inputs(s));
  const Decoded d = decode(read_file(path));
  std::filesystem::remove(path);
  ASSERT_EQ(d.width, L.width);
  ASSERT_EQ(d.height, L.height);
  EXPECT_GE(L.width, 900);  // wide enough for the footer text
  // Panels cover the 80 mm box, at least 240 pixels wide (1/3 mm pixels here,
  // finer than the 1 mm smallest spacing).
  EXPECT_DOUBLE_EQ(L.pixel_mm, 80.0 / 240.0);
  for (const auto& row : L.panels)
    for (const ReportRect& p : row) {
      EXPECT_EQ(p.width, 240);
      EXPECT_GE(p.x, 0);
      EXPECT_LE(p.x + p.width, L.width);
      EXPECT_LE(p.y + p.height, L.height);
    }
  // The title and the key numbers are text: many inked pixels, in the text colour.
  EXPECT_GT(inked(d, L.title), 300);
  EXPECT_GT(inked(d, L.numbers), 1000);
  // The result band is green for a non-rigid result.
  const Rgb band = d.at(L.result_band.x + L.result_band.width - 3, L.result_band.y + 2);
  EXPECT_EQ(band, (Rgb{30, 110, 50}));
  // One swatch per legend entry, filled with exactly the table's colour.
  ASSERT_EQ(L.legend_swatches.size(), 3u);
  const std::array<Rgb, 3> colours{kBrain, kVentricles, kTumour};
  for (std::size_t i = 0; i < 3; ++i) {
    const ReportRect& r = L.legend_swatches[i];
    EXPECT_EQ(d.at(r.x + r.width / 2, r.y + r.height / 2), colours[i]) << i;
  }
  // The scale bar is 1 cm: 30 pixels of 1/3 mm, white.
  EXPECT_EQ(L.scale_bar.width, 30);
  EXPECT_EQ(d.at(L.scale_bar.x + 15, L.scale_bar.y + 2), (Rgb{255, 255, 255}));
  // Row 1 holds the brain and tumour contours in the table's colours.
  int green = 0, yellow = 0;
  for (const ReportRect& p : L.panels[0])
    for (int y = p.y; y < p.y + p.height; ++y)
      for (int x = p.x; x < p.x + p.width; ++x) {
        green += d.at(x, y) == kBrain;
        yellow += d.at(x, y) == kTumour;
      }
  EXPECT_GT(green, 100);
  EXPECT_GT(yellow, 20);
}

// The difference rows away from the markers (their corners are labelled):
// the misaligned affine row is bright, the perfect non-rigid row black.
TEST(Report, DifferenceRowsShowTheMisalignment) {
  const Scene s = make_scene();
  ReportLayout L;
  const Decoded d = decode(report_png_bytes(inputs(s), {}, &L));
  long row2 = 0, row3 = 0;
  for (int v = 0; v < 3; ++v) {
    const ReportRect a = L.panels[1][v], b = L.panels[2][v];
    for (int y = 30; y < a.height - 30; ++y)
      for (int x = 30; x < a.width - 30; ++x) {
        row2 += d.at(a.x + x, a.y + y)[0];
        row3 += d.at(b.x + x, b.y + y)[0];
      }
  }
  EXPECT_GT(row2, 1000);
  EXPECT_EQ(row3, 0);
}

TEST(Report, FallbackIsMarkedInTheTitleBand) {
  const Scene s = make_scene();
  ReportInputs nonrigid = inputs(s), fallback = inputs(s);
  fallback.summary.fallback = true;
  fallback.summary.fallback_reason =
      "the non-rigid field folds (min Jacobian determinant -0.020000), and this reason is long enough that it "
      "has to wrap onto a second line of the band to be read in full";
  ReportLayout Ln, Lf;
  const Decoded dn = decode(report_png_bytes(nonrigid, {}, &Ln));
  const Decoded df = decode(report_png_bytes(fallback, {}, &Lf));
  EXPECT_EQ(df.at(Lf.result_band.x + Lf.result_band.width - 3, Lf.result_band.y + 2), (Rgb{170, 30, 30}));
  // The long reason wraps: a taller band, and the page grows with it.
  EXPECT_GT(Lf.result_band.height, Ln.result_band.height);
  EXPECT_EQ(Lf.height - Ln.height, Lf.result_band.height - Ln.result_band.height);
  // The band's text differs (not only its colour): compare which pixels are text.
  int differing = 0;
  for (int y = Ln.result_band.y; y < Ln.result_band.y + Ln.result_band.height; ++y)
    for (int x = Ln.result_band.x; x < Ln.result_band.x + 400; ++x) {
      const bool text_n = dn.at(x, y) != (Rgb{30, 110, 50}), text_f = df.at(x, y) != (Rgb{170, 30, 30});
      differing += text_n != text_f;
    }
  EXPECT_GT(differing, 100);
}

// A non-rigid result to be read with care (given labels the image's
// refinement changed grossly) says so on an amber band, not the green one.
TEST(Report, ACautionIsMarkedInTheTitleBand) {
  const Scene s = make_scene();
  ReportInputs in = inputs(s);
  in.summary.caution = "brain the given labels lack: 131 ml, up to 17 mm deep, centred at (40, 10, 5) mm RAS";
  ReportLayout L;
  const Decoded d = decode(report_png_bytes(in, {}, &L));
  EXPECT_EQ(d.at(L.result_band.x + L.result_band.width - 3, L.result_band.y + 2), (Rgb{165, 95, 0}));
  // A fallback's red wins over a caution.
  in.summary.fallback = true;
  const Decoded f = decode(report_png_bytes(in, {}, &L));
  EXPECT_EQ(f.at(L.result_band.x + L.result_band.width - 3, L.result_band.y + 2), (Rgb{170, 30, 30}));
}

// A fifth structure in the table gets its swatch and its contour colour.
TEST(Report, LegendFollowsTheLabelTable) {
  Scene s = make_scene();
  for (int k = 10; k < 20; ++k)
    for (int j = 30; j < 40; ++j)
      for (int i = 20; i < 30; ++i) s.labels.at(i, j, k) = 5;
  ReportInputs in = inputs(s);
  const Rgb arcuate{150, 90, 255};
  in.legend.push_back({5, "arcuate_fasciculus", arcuate});
  ReportOptions opt;
  opt.centre_mm = s.labels.grid.world_mm(25, 35, 15);
  ReportLayout L;
  const Decoded d = decode(report_png_bytes(in, opt, &L));
  ASSERT_EQ(L.legend_swatches.size(), 4u);
  const ReportRect& sw = L.legend_swatches[3];
  EXPECT_EQ(d.at(sw.x + 7, sw.y + 7), arcuate);
  int purple = 0;
  for (const ReportRect& p : L.panels[0])
    for (int y = p.y; y < p.y + p.height; ++y)
      for (int x = p.x; x < p.x + p.width; ++x) purple += d.at(x, y) == arcuate;
  EXPECT_GT(purple, 20);
}

// The uncertainty map adds a fourth row: its band in colour where it claims
// an answer, low (blue) in one half of the brain and high (red) in the other,
// and a colour bar in mm whose ends are those colours.
TEST(Report, UncertaintyRowShowsTheBandWithItsColourBar) {
  const Scene s = make_scene();
  ReportLayout without;
  report_png_bytes(inputs(s), {}, &without);
  EXPECT_EQ(without.uncertainty_panels[0].width, 0);
  EXPECT_EQ(without.uncertainty_bar.width, 0);

  ImageF band(s.labels.grid, 0.f);
  for (std::size_t v = 0; v < band.voxels.size(); ++v)
    if (s.labels.voxels[v] != 0) band.voxels[v] = s.labels.grid.world_mm(v % 80, (v / 80) % 80, v / 6400).x() < 0 ? 0.5f : 3.8f;
  ReportInputs in = inputs(s);
  in.uncertainty_mm = &band;
  ReportOptions opt;
  opt.centre_mm = Eigen::Vector3d(0, 0, 0);
  ReportLayout L;
  const Decoded d = decode(report_png_bytes(in, opt, &L));
  ASSERT_EQ(d.height, L.height);
  EXPECT_GT(L.height, without.height);
  EXPECT_DOUBLE_EQ(L.uncertainty_max_mm, 4.0);  // 3.8 rounded up to 0.5 mm
  const ReportRect axial = L.uncertainty_panels[0];
  ASSERT_EQ(axial.width, L.panels[2][0].width);
  EXPECT_GT(axial.y, L.panels[2][0].y);
  // 20 mm left and right of the centre on the axial slice (R to the right).
  const int cy = axial.y + axial.height / 2, offset = static_cast<int>(20 / L.pixel_mm);
  const Rgb low = d.at(axial.x + axial.width / 2 - offset, cy), high = d.at(axial.x + axial.width / 2 + offset, cy);
  EXPECT_GT(low[2], low[0]) << "a small band is blue";
  EXPECT_GT(high[0], high[2] + 60) << "a large band is red";
  const ReportRect bar = L.uncertainty_bar;
  ASSERT_GT(bar.width, 50);
  EXPECT_GT(d.at(bar.x + 1, bar.y + 5)[2], d.at(bar.x + 1, bar.y + 5)[0]);
  EXPECT_GT(d.at(bar.x + bar.width - 2, bar.y + 5)[0], d.at(bar.x + bar.width - 2, bar.y + 5)[2]);
  EXPECT_GT(inked(d, {bar.x, bar.y + 12, bar.width, 16}), 20) << "its ends are labelled in mm";
}

// A field of view that cuts the brain is said among the key numbers; a
// whole brain in view adds no row.
TEST(Report, ABrainCutByTheFieldOfViewAddsAKeyNumber) {
  const Scene s = make_scene();
  ReportLayout plain, whole, cut;
  report_png_bytes(inputs(s), {}, &plain);
  ReportInputs in = inputs(s);
  in.summary.brain_in_view_fraction = 1.0;
  report_png_bytes(in, {}, &whole);
  EXPECT_EQ(whole.numbers.height, plain.numbers.height);
  in.summary.brain_in_view_fraction = 0.72;
  report_png_bytes(in, {}, &cut);
  EXPECT_EQ(cut.numbers.height, plain.numbers.height + 18);
}

TEST(Report, PixelSizeOptionScalesPanelsAndScaleBar) {
  const Scene s = make_scene();
  ReportOptions opt;
  opt.pixel_mm = 0.25;
  opt.centre_mm = Eigen::Vector3d(0, 0, 0);
  ReportLayout L;
  const std::string bytes = report_png_bytes(inputs(s), opt, &L);
  EXPECT_EQ(L.panels[0][0].width, 320);
  EXPECT_EQ(L.scale_bar.width, 40);
  EXPECT_EQ(bytes.substr(1, 3), "PNG");
}

TEST(Report, RejectsMissingInputsBadOptionsAndUnwritablePaths) {
  const Scene s = make_scene();
  ReportInputs missing = inputs(s);
  missing.warped_preop_affine = nullptr;
  EXPECT_THROW(report_png_bytes(missing), InputError);
  ReportOptions bad;
  bad.difference_window = 0;
  EXPECT_THROW(report_png_bytes(inputs(s), bad), InputError);
  EXPECT_THROW(write_report_png("/nonexistent-dir/x.png", inputs(s)), InputError);
}

}  // namespace
}  // namespace brainshift
