#pragma once
// The registration report picture (after Figure 4 of the brain-shift papers):
//
//   columns: axial, coronal, sagittal slices through one world point;
//   row 1:   the intraop image with the contours of the warped preop
//            structures (brain green, ventricles cyan, corticospinal tract
//            red, tumour yellow; other labels magenta);
//   row 2:   |intraop - warped preop| after the affine stage only;
//   row 3:   |intraop - warped preop| after the non-rigid correction.
//
// Slices are resampled through world coordinates onto square pixels (any
// voxel spacing or orientation), shown in neurological convention: axial and
// coronal with the patient's right on the right, axial anterior up, coronal
// and sagittal superior up, sagittal anterior on the right. Intensities of
// each image are normalised by their 99th percentile inside the brain before
// differencing, so differently scaled scans are comparable; rows 2 and 3 use
// the same window, so darker means better aligned.
#include <Eigen/Dense>
#include <filesystem>
#include <optional>
#include <string>

#include "core/image.h"

namespace brainshift {

struct ReportInputs {
  const ImageF* intraop = nullptr;                // required
  const ImageF* warped_preop_affine = nullptr;    // required, preop T1 after the affine only
  const ImageF* warped_preop_nonrigid = nullptr;  // required, after the full correction
  const LabelImage* warped_labels = nullptr;      // required, preop labels after the full correction
};

struct ReportOptions {
  // World point (RAS mm) the three slices pass through. Default: the centroid
  // of tumour_label in warped_labels when present, else of all non-zero labels.
  std::optional<Eigen::Vector3d> centre_mm;
  std::uint16_t tumor_label = 4;
  // Square pixel size; 0 = the smallest voxel spacing of the intraop grid.
  double pixel_mm = 0;
  // Difference window in normalised intensity units (0 black .. this white).
  double difference_window = 0.4;
};

struct ReportImageSize {
  int width = 0, height = 0;
};

// PNG file contents (RGB, 8 bit). InputError on missing inputs.
std::string report_png_bytes(const ReportInputs& inputs, const ReportOptions& options = {},
                             ReportImageSize* size = nullptr);
// Writes the PNG; InputError naming the path when it cannot be written.
ReportImageSize write_report_png(const std::filesystem::path& path, const ReportInputs& inputs,
                                 const ReportOptions& options = {});

}  // namespace brainshift
