#pragma once
// The report's nine image panels as RGB rasters (report.h describes them);
// the page around them is drawn in report.cpp.
#include <array>
#include <cstdint>
#include <vector>

#include "report/report.h"

namespace brainshift::report_detail {

struct Raster {
  int size = 0;                    // square, size x size pixels
  std::vector<std::uint8_t> rgb;   // row-major, top row first
};

struct Panels {
  double pixel_mm = 1;
  int size = 0;
  Eigen::Vector3d centre_mm = Eigen::Vector3d::Zero();  // the point all slices pass through
  std::array<std::array<Raster, 3>, 3> rows;            // [row][axial, coronal, sagittal]
  std::array<Raster, 3> uncertainty;                    // row 4, when the map is given
  double uncertainty_max_mm = 0;                        // its colour scale's top
};

// The uncertainty colour scale at t in [0, 1]: blue, yellow, red.
LabelColour uncertainty_colour(double t);

// The in-plane world axes (screen right, screen up) of each view.
struct View {
  Eigen::Vector3d right, up;
};
const std::array<View, 3>& views();

Panels paint_panels(const ReportInputs& inputs, const ReportOptions& options);

}  // namespace brainshift::report_detail
