// The DICOM series reader against series written here from a phantom volume
// with DCMTK (engine/phantom/phantom_dicom.h) and against Debian's dcm2niix, a
// converter nobody here wrote, on the same files: same voxels, same world
// geometry within 1e-3 mm at the corners, for axial, coronal, sagittal and
// oblique slices and several patient positions; and every refusal.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>

#include "core/errors.h"
#include "phantom/phantom_dicom.h"
#include "e2e/process.h"
#include "image/dicom_series.h"
#include "image/nifti_io.h"
#include "synthetic_head.h"
#include "temp_dir.h"

using namespace brainshift;
namespace fs = std::filesystem;

namespace {

const ImageF& phantom() {
  static const ImageF t1 = test::synthetic_head().t1;
  return t1;
}

constexpr std::size_t kMaxBytes = std::size_t{1} << 30;

std::string refusal(const fs::path& dir, const std::string& uid = "") {
  try {
    read_dicom_series(dir, uid, kMaxBytes);
  } catch (const InputError& e) {
    return e.what();
  }
  return "(read without error)";
}

// dcm2niix's NIfTI of the series in dir.
ImageF dcm2niix(const fs::path& dir, const fs::path& work) {
  const fs::path out = work / "dcm2niix";
  fs::create_directories(out);
  const auto r = e2e::run({DCM2NIIX_BIN, "-z", "n", "-b", "n", "-f", "converted", "-o", out.string(), dir.string()},
                          work, 120);
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  return read_scalar_image(out / "converted.nii", kMaxBytes);
}

// Every voxel of `ours` is a voxel of `theirs` at the same world point (within
// 1e-3 mm) with the same value; the corners are checked by the same rule.
void expect_same_volume(const ImageF& ours, const ImageF& theirs) {
  ASSERT_EQ(ours.grid.voxel_count(), theirs.grid.voxel_count());
  const Eigen::Matrix4d to_theirs = theirs.grid.voxel_from_world() * ours.grid.world_from_voxel;
  double worst_mm = 0, worst_value = 0;
  for (int k = 0; k < ours.grid.dims[2]; ++k)
    for (int j = 0; j < ours.grid.dims[1]; ++j)
      for (int i = 0; i < ours.grid.dims[0]; ++i) {
        const Eigen::Vector3d v = (to_theirs * Eigen::Vector4d(i, j, k, 1)).head<3>();
        const Eigen::Vector3i n(static_cast<int>(std::lround(v.x())), static_cast<int>(std::lround(v.y())),
                                static_cast<int>(std::lround(v.z())));
        ASSERT_TRUE(theirs.grid.contains(n.x(), n.y(), n.z())) << i << " " << j << " " << k;
        worst_mm = std::max(worst_mm, (theirs.grid.world_mm(n.x(), n.y(), n.z()) - ours.grid.world_mm(i, j, k)).norm());
        worst_value = std::max(worst_value, static_cast<double>(std::abs(theirs.at(n.x(), n.y(), n.z()) - ours.at(i, j, k))));
      }
  EXPECT_LT(worst_mm, 1e-3) << "world positions differ";
  EXPECT_LT(worst_value, 1e-3) << "voxel values differ";
}

struct Case {
  const char* name;
  Eigen::Vector3d row, col;
  const char* patient_position;
  double slope, intercept;
};

std::vector<Case> cases() {
  const Eigen::Matrix3d tilt =
      Eigen::AngleAxisd(0.4, Eigen::Vector3d(0.2, 1.0, 0.3).normalized()).toRotationMatrix();
  return {
      {"axial_hfs", {1, 0, 0}, {0, 1, 0}, "HFS", 1.0, 0.0},
      {"axial_ffs", {-1, 0, 0}, {0, 1, 0}, "FFS", 2.5, -100.0},
      {"axial_hfp", {-1, 0, 0}, {0, -1, 0}, "HFP", 0.5, 10.0},
      {"coronal", {1, 0, 0}, {0, 0, -1}, "HFS", 1.0, 0.0},
      {"sagittal", {0, 1, 0}, {0, 0, -1}, "HFS", 1.0, -1024.0},
      {"oblique", tilt * Eigen::Vector3d(1, 0, 0), tilt * Eigen::Vector3d(0, 1, 0), "HFS", 0.25, 0.0},
  };
}

DicomSeriesSpec spec_for(const Case& c) {
  DicomSeriesSpec s;
  s.row_dir_lps = c.row;
  s.col_dir_lps = c.col;
  s.patient_position = c.patient_position;
  s.rescale_slope = c.slope;
  s.rescale_intercept = c.intercept;
  // The stack's centre at the phantom's centre, whatever the orientation.
  const Eigen::Vector3d normal = c.row.cross(c.col);
  const Eigen::Vector3d half = c.row * s.column_spacing_mm * (s.columns - 1) / 2 +
                               c.col * s.row_spacing_mm * (s.rows - 1) / 2 +
                               normal * s.slice_spacing_mm * (s.slices - 1) / 2;
  s.first_position_lps = Eigen::Vector3d(0, 0, 5) - half;
  return s;
}

}  // namespace

TEST(DicomSeries, EveryOrientationAsWrittenAndAsDcm2niixReadsIt) {
  test::TempDir dir;
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const fs::path series = dir.path() / c.name;
    const auto spec = spec_for(c);
    ImageF expected;
    write_dicom_series(phantom(), series, spec, &expected);
    const ImageF ours = read_dicom_series(series, "", kMaxBytes);
    EXPECT_LT(ours.grid.max_voxel_offset_mm(dicom_series_grid_ras(spec)), 1e-6);
    ASSERT_EQ(ours.voxels.size(), expected.voxels.size());
    EXPECT_EQ(ours.voxels, expected.voxels);
    // Not a blank volume: the phantom's brain is in it.
    EXPECT_GT(*std::max_element(ours.voxels.begin(), ours.voxels.end()), 90.0f);
    expect_same_volume(ours, dcm2niix(series, dir.path() / (std::string(c.name) + "_work")));
  }
}

TEST(DicomSeries, ShuffledFileNamesAreSortedByPositionNotByName) {
  test::TempDir dir;
  auto spec = spec_for(cases()[5]);
  write_dicom_series(phantom(), dir.path() / "ordered", spec);
  spec.shuffle_seed = 7;
  write_dicom_series(phantom(), dir.path() / "shuffled", spec);
  const ImageF a = read_dicom_series(dir.path() / "ordered", "", kMaxBytes);
  const ImageF b = read_dicom_series(dir.path() / "shuffled", "", kMaxBytes);
  EXPECT_TRUE(a.grid.same_geometry(b.grid));
  EXPECT_EQ(a.voxels, b.voxels);
}

TEST(DicomSeries, MissingSlicesAreRefusedNamingWhatIsMissing) {
  test::TempDir dir;
  const auto files = write_dicom_series(phantom(), dir.path() / "s", spec_for(cases()[0]));
  fs::remove(files[7]);  // InstanceNumber 8
  fs::remove(files[8]);
  const std::string why = refusal(dir.path() / "s");
  EXPECT_NE(why.find("2 slice(s) missing"), std::string::npos) << why;
  EXPECT_NE(why.find("InstanceNumber 8, 9 missing"), std::string::npos) << why;
}

// The series names its patient (for the check that a scan is of the preop's
// patient, DESIGN.md "Patient identity"); slices of two patients under one
// series UID (a resend mixed with another exam) are not one volume.
TEST(DicomSeries, ThePatientIsReadAndSlicesOfTwoPatientsAreRefused) {
  test::TempDir dir;
  auto spec = spec_for(cases()[0]);
  spec.series_uid = "1.2.826.0.1.3680043.2.1125.1.7";
  spec.patient_id = "MRN-0042";
  const auto files = write_dicom_series(phantom(), dir.path() / "a", spec);
  std::string patient;
  read_dicom_series(dir.path() / "a", "", kMaxBytes, &patient);
  EXPECT_EQ(patient, "MRN-0042");
  spec.patient_id = "MRN-0043";
  const auto other = write_dicom_series(phantom(), dir.path() / "b", spec);
  fs::copy_file(other[5], files[5], fs::copy_options::overwrite_existing);
  const std::string why = refusal(dir.path() / "a");
  EXPECT_NE(why.find("slices of two patients"), std::string::npos) << why;
  EXPECT_NE(why.find("MRN-0043"), std::string::npos) << why;
  // A European site's Latin-1 (ISO_IR 100): one byte for the umlaut, read
  // as UTF-8, which the protocol carries.
  spec.specific_character_set = "ISO_IR 100";
  spec.patient_id = "M\xDCLLER-7";
  write_dicom_series(phantom(), dir.path() / "latin1", spec);
  read_dicom_series(dir.path() / "latin1", "", kMaxBytes, &patient);
  EXPECT_EQ(patient, "M\xC3\x9CLLER-7");
}

TEST(DicomSeries, SeveralSeriesAreListedAndOneIsChosenByUid) {
  test::TempDir dir;
  auto a = spec_for(cases()[0]);
  a.series_uid = "1.2.826.0.1.3680043.2.1125.1.1";
  auto b = spec_for(cases()[3]);
  b.series_uid = "1.2.826.0.1.3680043.2.1125.1.2";
  b.series_description = "coronal";
  write_dicom_series(phantom(), dir.path() / "exam" / "a", a);
  write_dicom_series(phantom(), dir.path() / "exam" / "b", b);
  const std::string why = refusal(dir.path() / "exam");
  EXPECT_NE(why.find("2 series"), std::string::npos) << why;
  EXPECT_NE(why.find(a.series_uid), std::string::npos) << why;
  EXPECT_NE(why.find(b.series_uid + "  MR  24 file(s)  \"coronal\""), std::string::npos) << why;
  const auto listed = list_dicom_series(dir.path() / "exam");
  ASSERT_EQ(listed.size(), 2u);
  const ImageF chosen = read_dicom_series(dir.path() / "exam", b.series_uid, kMaxBytes);
  EXPECT_LT(chosen.grid.max_voxel_offset_mm(dicom_series_grid_ras(b)), 1e-6);
  EXPECT_NE(refusal(dir.path() / "exam", "1.2.3").find("no series 1.2.3"), std::string::npos);
}

TEST(DicomSeries, GantryTiltAndBadFoldersAreRefused) {
  test::TempDir dir;
  auto spec = spec_for(cases()[0]);
  spec.tilt_mm_per_slice = 0.8;  // about 10 degrees at 4.5 mm slices
  write_dicom_series(phantom(), dir.path() / "tilt", spec);
  EXPECT_NE(refusal(dir.path() / "tilt").find("gantry tilt"), std::string::npos) << refusal(dir.path() / "tilt");

  fs::create_directories(dir.path() / "none");
  std::ofstream(dir.path() / "none" / "notes.txt") << "not DICOM\n";
  EXPECT_NE(refusal(dir.path() / "none").find("no DICOM image files"), std::string::npos);
  EXPECT_NE(refusal(dir.path() / "absent").find("not a folder"), std::string::npos);

  // Two copies of one slice (a file copied twice under another name).
  const auto files = write_dicom_series(phantom(), dir.path() / "dup", spec_for(cases()[0]));
  fs::copy_file(files[3], dir.path() / "dup" / "copy.dcm");
  EXPECT_NE(refusal(dir.path() / "dup").find("at one position"), std::string::npos) << refusal(dir.path() / "dup");

  // Too many voxels for the bound.
  write_dicom_series(phantom(), dir.path() / "big", spec_for(cases()[0]));
  try {
    read_dicom_series(dir.path() / "big", "", 1000);
    FAIL() << "no bound";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("MB allowed"), std::string::npos) << e.what();
  }
}
