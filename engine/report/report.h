#pragma once
// report.png: one registration on one page, for the surgeon and the record.
//
//   title:   the scan id and the result kind (non-rigid on a green band, or
//            with a caution on an amber one, or the affine-only fallback
//            with its reason on a red band);
//   columns: axial, coronal, sagittal slices through one world point (their
//            RAS position in the column header);
//   row 1:   the intraop image with the contours of the warped preop
//            structures in their label-table colours;
//   row 2:   |intraop - warped preop| after the affine stage only;
//   row 3:   |intraop - warped preop| after the non-rigid correction;
//   row 4:   (when the uncertainty map is given) its 95 % band radius in
//            colour over the intraop image, with a colour bar in mm;
//   footer:  the colour legend (label table), the key numbers (Dice and mean
//            surface distance affine-only and final, min Jacobian determinant,
//            worst surface residual), the difference scale and the display
//            convention.
//
// Display convention: neurological (patient's right on the image's right),
// marked on every panel with L/R and A/P (or S/I): axial anterior up, coronal
// and sagittal superior up, sagittal anterior on the right. A 1 cm scale bar
// sits in every row-1 panel. Slices are resampled through world coordinates
// onto square pixels (any voxel spacing or orientation). Intensities of each
// image are normalised by their 99th percentile inside the brain before
// differencing, so differently scaled scans are comparable; rows 2 and 3 use
// the same window, so darker means better aligned.
//
// Drawn with Cairo and encoded by Cairo's PNG writer, the project's one.
#include <Eigen/Dense>
#include <array>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "core/image.h"
#include "core/label_colour.h"

namespace brainshift {

struct ReportLegendEntry {
  std::uint16_t value = 0;
  std::string name;
  LabelColour colour{};
};

// The text of the page. Numbers that are absent print as "n/a".
struct ReportSummary {
  std::string scan_id;
  bool fallback = false;        // the affine-only fallback result
  std::string fallback_reason;  // why, when fallback
  // A non-rigid result to be read with care, and why (e.g. given labels the
  // image's refinement changed grossly): the result line turns amber.
  std::string caution;
  struct Overlap {
    std::string structure;
    std::optional<double> dice_affine, dice, mean_distance_affine_mm, mean_distance_mm;
  };
  std::vector<Overlap> overlaps;  // structures the intraop segmentation has
  std::optional<double> min_jacobian;
  std::optional<double> worst_residual_mm;  // largest surface-match residual
  std::string worst_residual_surface;
  // The uncertainty map (95 % band radius over the brain) when it was made.
  std::optional<double> uncertainty_median_mm, uncertainty_p95_mm;
  // The share of the preop brain the intraop field of view holds (the
  // plausibility volume gate's); a row is printed only when part is cut off,
  // where the answer is the model's continuation, not a match.
  std::optional<double> brain_in_view_fraction;
  // Replaces the result line when set (a picture of something other than a
  // registration, e.g. a phantom's ground truth).
  std::string result_text;
};

struct ReportInputs {
  const ImageF* intraop = nullptr;                // required
  const ImageF* warped_preop_affine = nullptr;    // required, preop T1 after the affine only
  const ImageF* warped_preop_nonrigid = nullptr;  // required, after the full correction
  const LabelImage* warped_labels = nullptr;      // required, preop labels after the full correction
  // Contour colours and the legend. outer_label's contour is the outline of
  // every non-zero label (the brain surface); other labels by value. A value
  // not in the legend is drawn magenta.
  std::vector<ReportLegendEntry> legend;
  std::uint16_t outer_label = 1;
  ReportSummary summary;
  // Optional: the intraop segmentation the engine derived from the image (a
  // scan given without labels), its brain outline and ventricles drawn in
  // row 1 as a dotted white contour over the preop's, so the surgeon sees
  // what the registration was matched to.
  const LabelImage* segmentation = nullptr;
  // Optional: the uncertainty map (95 % band radius, mm, intraop grid): a
  // fourth row, colour from 0 to its 99th percentile over the brain.
  const ImageF* uncertainty_mm = nullptr;
};

struct ReportOptions {
  // World point (RAS mm) the three slices pass through. Default: the centroid
  // of centre_label in warped_labels when present, else of all non-zero labels.
  std::optional<Eigen::Vector3d> centre_mm;
  std::uint16_t centre_label = 0;
  // Square pixel size; 0 = the smallest voxel spacing of the intraop grid, or
  // less when that would make a panel narrower than 240 pixels.
  double pixel_mm = 0;
  // Difference window in normalised intensity units (0 black .. this white).
  double difference_window = 0.4;
};

// Where things were drawn (pixels, origin top left), for tests and callers.
struct ReportRect {
  int x = 0, y = 0, width = 0, height = 0;
};
struct ReportLayout {
  int width = 0, height = 0;
  double pixel_mm = 0;
  ReportRect title;        // the title line (scan id)
  ReportRect result_band;  // the result line: green band, amber with a caution, red for the fallback
  std::array<std::array<ReportRect, 3>, 3> panels{};  // [row][axial, coronal, sagittal]
  std::vector<ReportRect> legend_swatches;            // one per legend entry, filled with its colour
  ReportRect numbers;                                 // the key-numbers table
  ReportRect scale_bar;                               // the 1 cm bar of the first panel
  std::array<ReportRect, 3> uncertainty_panels{};     // row 4; empty without the map
  ReportRect uncertainty_bar;                         // its colour bar; empty without the map
  double uncertainty_max_mm = 0;                      // the colour bar's top
};

// PNG file contents (RGB, 8 bit). InputError on missing inputs or bad options.
std::string report_png_bytes(const ReportInputs& inputs, const ReportOptions& options = {},
                             ReportLayout* layout = nullptr);
// Writes the PNG; InputError naming the path when it cannot be written.
ReportLayout write_report_png(const std::filesystem::path& path, const ReportInputs& inputs,
                              const ReportOptions& options = {});

}  // namespace brainshift
