#pragma once
// A DICOM image series (one slice per file, as MR and CT scanners send them)
// read with DCMTK into the project's world frame, RAS+ mm.
//
// Geometry comes from the patient-based attributes only:
// ImageOrientationPatient gives the row and column directions, the slices
// are sorted by ImagePositionPatient along their normal (not by file name
// or InstanceNumber), and the slice spacing is the distance between those
// positions (SliceThickness and SpacingBetweenSlices are not used: scanners
// write overlapping or gapped slices). PatientPosition (HFS, FFS, ...) needs
// no handling: the positions and orientations are already in the patient's
// LPS frame; the one LPS->RAS conversion is engine/field/lps.h's.
//
// Voxel (i, j, k) is column i and row j of the k-th slice in position order,
// value = stored value * RescaleSlope + RescaleIntercept.
//
// Refused with an InputError naming the folder and the reason: a folder with
// several series and no series UID given (the series are listed), slices of
// different size, spacing or orientation, a gantry tilt (the slice positions
// do not advance along the normal), non-uniform slice spacing or missing
// slices (the gap and the InstanceNumbers missing are named), two slices at
// one position, multi-frame objects, compressed pixel data, colour images,
// slices of different PatientIDs.
#include <cstddef>
#include <filesystem>
#include <string>
#include <vector>

#include "core/image.h"

namespace brainshift {

struct DicomSeriesSummary {
  std::string series_uid;
  std::string description;  // SeriesDescription, may be empty
  std::string modality;
  std::size_t files = 0;
};

// The image series in a folder (searched recursively; files that are not
// DICOM, e.g. a DICOMDIR or notes, are skipped).
std::vector<DicomSeriesSummary> list_dicom_series(const std::filesystem::path& dir);

// Reads the series series_uid ("" when the folder holds only one) as a
// float image; max_image_bytes bounds the voxels (4 bytes each).
// patient_id, when given, receives the series' PatientID (0010,0020) in
// UTF-8 (converted from the SpecificCharacterSet the files declare; as
// written when they declare none; "" when absent), for the check that
// preop and scan are of one patient (docs/DESIGN.md, "Patient identity").
ImageF read_dicom_series(const std::filesystem::path& dir, const std::string& series_uid,
                         std::size_t max_image_bytes, std::string* patient_id = nullptr);

// The largest distance (mm) by which a slice's position may differ from the
// uniform stack fitted through all of them, and an in-plane offset between
// slices may be (gantry tilt); why: docs/DESIGN.md, "DICOM slice tolerance".
double dicom_slice_tolerance_mm(double slice_spacing_mm);

}  // namespace brainshift
