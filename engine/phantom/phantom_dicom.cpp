#include "phantom/phantom_dicom.h"

#include <dcmtk/config/osconfig.h>
#include <dcmtk/dcmdata/dcdeftag.h>
#include <dcmtk/dcmdata/dcfilefo.h>
#include <dcmtk/dcmdata/dcuid.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>
#include <sstream>
#include <stdexcept>

#include "core/errors.h"
#include "field/lps.h"
#include "image/resample.h"

namespace brainshift {
namespace fs = std::filesystem;
namespace {

std::string ds(double v) {
  std::ostringstream os;
  os.precision(10);  // DS holds 16 characters
  os << v;
  return os.str();
}

std::string new_uid() {
  char buf[100];
  return dcmGenerateUniqueIdentifier(buf, SITE_INSTANCE_UID_ROOT);
}

void put(DcmDataset& d, const DcmTagKey& tag, const std::string& value) {
  if (d.putAndInsertString(tag, value.c_str()).bad()) throw std::runtime_error("DICOM writer: cannot set a tag");
}

}  // namespace

Grid3 dicom_series_grid_ras(const DicomSeriesSpec& s) {
  const Eigen::Vector3d normal = s.row_dir_lps.cross(s.col_dir_lps);
  Eigen::Matrix4d lps = Eigen::Matrix4d::Identity();
  lps.block<3, 1>(0, 0) = s.row_dir_lps * s.column_spacing_mm;
  lps.block<3, 1>(0, 1) = s.col_dir_lps * s.row_spacing_mm;
  lps.block<3, 1>(0, 2) = normal * s.slice_spacing_mm;
  lps.block<3, 1>(0, 3) = s.first_position_lps;
  Grid3 g;
  g.dims = {s.columns, s.rows, s.slices};
  g.world_from_voxel = ras_world_from_lps_world_matrix(lps);
  return g;
}

DicomSeriesSpec dicom_series_spec_of(const ImageF& image) {
  const Eigen::Matrix4d lps = lps_world_from_ras_world_matrix(image.grid.world_from_voxel);
  const Eigen::Vector3d spacing = image.grid.spacing_mm();
  DicomSeriesSpec s;
  s.row_dir_lps = lps.block<3, 1>(0, 0) / spacing[0];
  s.col_dir_lps = lps.block<3, 1>(0, 1) / spacing[1];
  if ((s.row_dir_lps.cross(s.col_dir_lps) - lps.block<3, 1>(0, 2) / spacing[2]).norm() > 1e-6)
    throw InputError("the image's third axis is not row x column (LPS): a DICOM series cannot hold its grid");
  s.first_position_lps = lps.block<3, 1>(0, 3);
  s.columns = image.grid.dims[0];
  s.rows = image.grid.dims[1];
  s.slices = image.grid.dims[2];
  s.column_spacing_mm = spacing[0];
  s.row_spacing_mm = spacing[1];
  s.slice_spacing_mm = spacing[2];
  s.slice_thickness_mm = spacing[2];
  const auto [lo, hi] = std::minmax_element(image.voxels.begin(), image.voxels.end());
  const double range = std::max(std::abs(static_cast<double>(*lo)), std::abs(static_cast<double>(*hi)));
  s.rescale_slope = range > 0 ? range / 30000.0 : 1.0;
  return s;
}

std::vector<fs::path> write_dicom_series(const ImageF& phantom, const fs::path& dir, const DicomSeriesSpec& s,
                                         ImageF* expected_values) {
  fs::create_directories(dir);
  const Grid3 grid = dicom_series_grid_ras(s);
  const ImageF values = resample_linear(phantom, grid);
  ImageF expected(grid);
  const std::string study = new_uid(), series = s.series_uid.empty() ? new_uid() : s.series_uid;
  const Eigen::Vector3d normal = s.row_dir_lps.cross(s.col_dir_lps);
  std::vector<int> name_of(static_cast<std::size_t>(s.slices));
  std::iota(name_of.begin(), name_of.end(), 1);
  if (s.shuffle_seed) std::shuffle(name_of.begin(), name_of.end(), std::mt19937(s.shuffle_seed));
  std::vector<fs::path> files;
  const std::size_t per_slice = static_cast<std::size_t>(s.columns) * s.rows;
  for (int k = 0; k < s.slices; ++k) {
    DcmFileFormat ff;
    DcmDataset& d = *ff.getDataset();
    put(d, DCM_SOPClassUID, UID_MRImageStorage);
    put(d, DCM_SOPInstanceUID, new_uid());
    put(d, DCM_StudyInstanceUID, study);
    put(d, DCM_SeriesInstanceUID, series);
    put(d, DCM_FrameOfReferenceUID, study + ".1");
    put(d, DCM_Modality, "MR");
    put(d, DCM_ImageType, "ORIGINAL\\PRIMARY\\M\\ND");
    put(d, DCM_PatientName, "Phantom^Brainshift");
    if (!s.specific_character_set.empty()) put(d, DCM_SpecificCharacterSet, s.specific_character_set);
    put(d, DCM_PatientID, s.patient_id);
    put(d, DCM_StudyDate, "20260101");
    put(d, DCM_StudyTime, "120000");
    put(d, DCM_SeriesDate, "20260101");
    put(d, DCM_SeriesTime, "120000");
    put(d, DCM_AcquisitionTime, "120000");
    put(d, DCM_SeriesDescription, s.series_description);
    put(d, DCM_ProtocolName, s.series_description);
    put(d, DCM_SeriesNumber, "3");
    put(d, DCM_AcquisitionNumber, "1");
    put(d, DCM_InstanceNumber, std::to_string(k + 1));
    put(d, DCM_PatientPosition, s.patient_position);
    put(d, DCM_EchoTime, "4.2");
    put(d, DCM_RepetitionTime, "2000");
    put(d, DCM_MagneticFieldStrength, "3");
    const Eigen::Vector3d pos =
        s.first_position_lps + k * s.slice_spacing_mm * normal + k * s.tilt_mm_per_slice * s.col_dir_lps;
    put(d, DCM_ImagePositionPatient, ds(pos.x()) + "\\" + ds(pos.y()) + "\\" + ds(pos.z()));
    const auto& r = s.row_dir_lps;
    const auto& c = s.col_dir_lps;
    put(d, DCM_ImageOrientationPatient,
        ds(r.x()) + "\\" + ds(r.y()) + "\\" + ds(r.z()) + "\\" + ds(c.x()) + "\\" + ds(c.y()) + "\\" + ds(c.z()));
    put(d, DCM_PixelSpacing, ds(s.row_spacing_mm) + "\\" + ds(s.column_spacing_mm));
    put(d, DCM_SliceThickness, ds(s.slice_thickness_mm));
    put(d, DCM_SliceLocation, ds(pos.dot(normal)));
    put(d, DCM_RescaleSlope, ds(s.rescale_slope));
    put(d, DCM_RescaleIntercept, ds(s.rescale_intercept));
    put(d, DCM_RescaleType, "US");
    d.putAndInsertUint16(DCM_Rows, static_cast<Uint16>(s.rows));
    d.putAndInsertUint16(DCM_Columns, static_cast<Uint16>(s.columns));
    d.putAndInsertUint16(DCM_SamplesPerPixel, 1);
    put(d, DCM_PhotometricInterpretation, "MONOCHROME2");
    d.putAndInsertUint16(DCM_BitsAllocated, 16);
    d.putAndInsertUint16(DCM_BitsStored, 16);
    d.putAndInsertUint16(DCM_HighBit, 15);
    d.putAndInsertUint16(DCM_PixelRepresentation, 1);
    std::vector<Uint16> pixels(per_slice);
    for (std::size_t i = 0; i < per_slice; ++i) {
      const double v = values.voxels[k * per_slice + i];
      const long stored = std::clamp(std::lround((v - s.rescale_intercept) / s.rescale_slope), -32768L, 32767L);
      pixels[i] = static_cast<Uint16>(static_cast<Sint16>(stored));
      expected.voxels[k * per_slice + i] = static_cast<float>(stored * s.rescale_slope + s.rescale_intercept);
    }
    if (d.putAndInsertUint16Array(DCM_PixelData, pixels.data(), static_cast<unsigned long>(pixels.size())).bad())
      throw std::runtime_error("DICOM writer: pixel data");
    const fs::path file = dir / ("IM" + std::to_string(name_of[static_cast<std::size_t>(k)]) + ".dcm");
    if (ff.saveFile(file.c_str(), EXS_LittleEndianExplicit).bad())
      throw std::runtime_error("DICOM writer: cannot write " + file.string());
    files.push_back(file);
  }
  if (expected_values) *expected_values = std::move(expected);
  return files;
}

}  // namespace brainshift
