#pragma once
// A phantom as the scanner would send it: a DICOM MR series written with
// DCMTK, the slices of a volume resampled onto the slice grid a scanner
// would describe, one single-frame file per slice, int16 stored values with a
// rescale. `brainshift phantom --dicom` and the tests' DICOM series (made
// here, never downloaded).
#include <filesystem>
#include <string>
#include <vector>

#include <Eigen/Dense>

#include "core/image.h"

namespace brainshift {

struct DicomSeriesSpec {
  // ImageOrientationPatient: the row direction (along which the column index
  // grows) and the column direction, unit vectors in LPS.
  Eigen::Vector3d row_dir_lps{1, 0, 0}, col_dir_lps{0, 1, 0};
  Eigen::Vector3d first_position_lps{-60, -70, -40};  // ImagePositionPatient of slice 0
  int columns = 40, rows = 36, slices = 24;
  double column_spacing_mm = 4.0, row_spacing_mm = 3.5;  // between columns, between rows
  double slice_spacing_mm = 4.5;                          // along row x col
  double slice_thickness_mm = 1.0;  // written on purpose unlike the spacing: readers must not use it
  std::string patient_position = "HFS";
  double rescale_slope = 1.0, rescale_intercept = 0.0;
  double tilt_mm_per_slice = 0.0;  // each slice shifted along the column direction (gantry tilt)
  std::string series_uid;          // generated when empty
  std::string series_description = "phantom T1";
  std::string patient_id = "PHANTOM01";  // PatientID (0010,0020), in specific_character_set
  std::string specific_character_set;    // (0008,0005); empty: not written (the default repertoire)
  unsigned shuffle_seed = 0;       // nonzero: file names in a random order of the slices
};

// The grid the spec describes, RAS+ (what a reader must give).
Grid3 dicom_series_grid_ras(const DicomSeriesSpec& spec);

// Writes the series into dir (created); returns the files in slice order.
// The voxel values are `phantom` sampled (linear) at the slice voxels,
// quantised to the stored int16 and rescaled back: expected_values gets
// exactly what a reader should return, on dicom_series_grid_ras(spec).
std::vector<std::filesystem::path> write_dicom_series(const ImageF& phantom, const std::filesystem::path& dir,
                                                      const DicomSeriesSpec& spec, ImageF* expected_values = nullptr);

// The spec of a series on image's own grid (a reader gives back that grid),
// the rescale chosen to keep the values to 1/30000 of their range. Throws
// InputError when the grid's third axis is not row x column in LPS (a
// series' slices stack along their normal).
DicomSeriesSpec dicom_series_spec_of(const ImageF& image);

}  // namespace brainshift
