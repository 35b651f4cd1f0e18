// NIfTI-2 input: a NIfTI-2 file reads into the same image as the NIfTI-1 file
// of the same data; its double geometry is kept; files written by the
// reference library (niftilib's nifti2_io) read back exactly; bad NIfTI-2
// headers are refused with messages that say what is wrong.
#include <gtest/gtest.h>
#include <nifti/nifti2_io.h>

#include <climits>
#include <cmath>
#include <limits>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "temp_dir.h"
#include "test_util.h"

namespace brainshift {
namespace {

constexpr std::size_t kLimit = std::size_t{1} << 30;

Grid3 oblique_grid() {
  Grid3 g;
  g.dims = {7, 5, 4};
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.4, Eigen::Vector3d(0.3, -0.5, 0.8).normalized()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = r * Eigen::Vector3d(0.9, 1.1, 2.5).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-80.5, 12.25, 30.0);
  return g;
}

ImageF ramp(const Grid3& g) {
  ImageF img(g);
  for (std::size_t i = 0; i < img.voxels.size(); ++i) img.voxels[i] = -3.5f + 0.75f * static_cast<float>(i % 41);
  return img;
}

LabelImage some_labels(const Grid3& g) {
  LabelImage l(g);
  for (std::size_t i = 0; i < l.voxels.size(); ++i) l.voxels[i] = static_cast<std::uint16_t>((i * 7) % 5);
  return l;
}

std::string as_nifti2(const std::string& nifti1_raw) {
  return test::nifti2_file(test::nifti2_header_of(nifti1_raw), test::nifti1_voxels(nifti1_raw));
}

void expect_same_grid_exactly(const Grid3& a, const Grid3& b) {
  EXPECT_EQ(a.dims, b.dims);
  EXPECT_EQ(a.world_from_voxel, b.world_from_voxel) << a.world_from_voxel << "\nvs\n" << b.world_from_voxel;
}

template <class Fn>
void expect_refused(Fn&& fn, const std::string& fragment) {
  try {
    fn();
    ADD_FAILURE() << "accepted; expected an InputError with '" << fragment << "'";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find(fragment), std::string::npos) << "expected '" << fragment << "' in: " << e.what();
  }
}

TEST(Nifti2, ScalarReadsLikeTheNifti1OfTheSameData) {
  for (VoxelType type : {VoxelType::float32, VoxelType::int16, VoxelType::uint8}) {
    const std::string n1 = scalar_image_to_bytes(ramp(oblique_grid()), type, false);
    const ImageF a = scalar_image_from_bytes(n1, "one.nii", kLimit);
    for (const std::string& n2 : {as_nifti2(n1), test::gzip(as_nifti2(n1))}) {
      const ImageF b = scalar_image_from_bytes(n2, "two.nii", kLimit);
      expect_same_grid_exactly(a.grid, b.grid);
      EXPECT_EQ(a.voxels, b.voxels);
    }
  }
}

TEST(Nifti2, LabelsAndDisplacementFieldReadLikeNifti1) {
  const std::string labels1 = label_image_to_bytes(some_labels(oblique_grid()), false);
  const LabelImage la = label_image_from_bytes(labels1, "l1", kLimit);
  const LabelImage lb = label_image_from_bytes(test::gzip(as_nifti2(labels1)), "l2", kLimit);
  expect_same_grid_exactly(la.grid, lb.grid);
  EXPECT_EQ(la.voxels, lb.voxels);

  VectorImage3 field(oblique_grid());
  for (std::size_t i = 0; i < field.vectors.size(); ++i)
    field.vectors[i] = Eigen::Vector3f(0.1f * static_cast<float>(i), -2.f, static_cast<float>(i % 3));
  const std::string field1 = displacement_field_to_bytes(field, false);
  const VectorImage3 fb = vector_image_from_bytes(as_nifti2(field1), "f2", kLimit);
  expect_same_grid_exactly(fb.grid, vector_image_from_bytes(field1, "f1", kLimit).grid);
  EXPECT_EQ(fb.vectors, field.vectors);
}

TEST(Nifti2, QformOnlyAndPixdimOnlyGeometryMatchNifti1) {
  std::string n1 = scalar_image_to_bytes(ramp(oblique_grid()), VoxelType::float32, false);
  test::poke<std::int16_t>(n1, test::offsets::sform_code, 0);  // geometry from the qform only
  const ImageF a = scalar_image_from_bytes(n1, "q1", kLimit);
  const ImageF b = scalar_image_from_bytes(as_nifti2(n1), "q2", kLimit);
  EXPECT_LT((a.grid.world_from_voxel - b.grid.world_from_voxel).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_LT((a.grid.world_from_voxel - oblique_grid().world_from_voxel).cwiseAbs().maxCoeff(), 1e-4);

  test::poke<std::int16_t>(n1, test::offsets::qform_code, 0);  // neither: diag(pixdim)
  const ImageF c = scalar_image_from_bytes(as_nifti2(n1), "p2", kLimit);
  EXPECT_NEAR(c.grid.world_from_voxel(0, 0), 0.9, 1e-6);
  EXPECT_NEAR(c.grid.world_from_voxel(2, 2), 2.5, 1e-6);
  EXPECT_EQ(c.grid.world_from_voxel(0, 3), 0.0);
}

TEST(Nifti2, DoubleSformIsKeptBeyondFloatPrecision) {
  nifti_2_header h = test::nifti2_header_of(scalar_image_to_bytes(ramp(oblique_grid()), VoxelType::float32, false));
  const double x0 = -80.123456789012345, s = 0.987654321098765;
  const double row_x[4] = {s, 1e-9, 0.0, x0};
  std::copy(row_x, row_x + 4, h.srow_x);
  h.srow_y[0] = 0; h.srow_y[1] = s; h.srow_y[2] = 0; h.srow_y[3] = 12.000000000123;
  h.srow_z[0] = 0; h.srow_z[1] = 0; h.srow_z[2] = 2.5; h.srow_z[3] = 30.0;
  const std::string voxels(7 * 5 * 4 * 4, '\0');
  const ImageF img = scalar_image_from_bytes(test::nifti2_file(h, voxels), "precise.nii", kLimit);
  EXPECT_EQ(img.grid.world_from_voxel(0, 3), x0);
  EXPECT_EQ(img.grid.world_from_voxel(0, 0), s);
  EXPECT_EQ(img.grid.world_from_voxel(0, 1), 1e-9);
  EXPECT_EQ(img.grid.world_from_voxel(1, 3), 12.000000000123);
  EXPECT_NE(static_cast<double>(static_cast<float>(x0)), x0) << "the test value must not fit a float";
}

// The reference library (niftilib) makes the headers from the same geometry:
// its NIfTI-1 file (nifti_image_write) and its NIfTI-2 header
// (nifti_convert_nim2n2hdr, whose magic ends in four zero bytes; niftilib
// 3.0.1 writes no single-file NIfTI-2 itself: after nifti_set_filenames its
// data overwrite the header) read as written.
TEST(Nifti2, HeadersMadeByNiftilibReadExactly) {
  const test::TempDir dir("nifti2");
  const Grid3 g = oblique_grid();
  const ImageF truth = ramp(g);
  const int64_t dims[8] = {3, g.dims[0], g.dims[1], g.dims[2], 1, 1, 1, 1};
  nifti_image* nim = nifti_make_new_nim(dims, DT_FLOAT32, 1);
  ASSERT_NE(nim, nullptr);
  std::memcpy(nim->data, truth.voxels.data(), truth.voxels.size() * sizeof(float));
  nim->sform_code = NIFTI_XFORM_SCANNER_ANAT;
  nim->qform_code = 0;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) nim->sto_xyz.m[r][c] = g.world_from_voxel(r, c);
  const std::string path1 = (dir / "lib1.nii.gz").string();
  ASSERT_EQ(nifti_set_filenames(nim, path1.c_str(), 0, 1), 0);
  nifti_image_write(nim);
  nim->nifti_type = NIFTI_FTYPE_NIFTI2_1;
  nifti_set_iname_offset(nim, 2);
  nifti_2_header h2{};
  ASSERT_EQ(nifti_convert_nim2n2hdr(nim, &h2), 0);
  nifti_image_free(nim);

  const ImageF one = read_scalar_image(path1);
  EXPECT_EQ(one.voxels, truth.voxels);
  EXPECT_LE((one.grid.world_from_voxel - g.world_from_voxel).cwiseAbs().maxCoeff(), 1e-5);  // float sform
  const std::string_view voxels(reinterpret_cast<const char*>(truth.voxels.data()), truth.voxels.size() * sizeof(float));
  h2.vox_offset = 544;  // niftilib fills it in only when it writes a file
  const ImageF two = scalar_image_from_bytes(test::gzip(test::nifti2_file(h2, voxels)), "lib2.nii.gz", kLimit);
  EXPECT_EQ(two.voxels, truth.voxels);
  EXPECT_EQ(two.grid.world_from_voxel, g.world_from_voxel);  // double sform: exact
}

TEST(Nifti2, BigEndianFileIsSwapped) {
  const std::string n1 = label_image_to_bytes(some_labels(oblique_grid()), false);  // uint8: no voxel swap
  nifti_2_header h = test::nifti2_header_of(n1);
  nifti_swap_as_nifti2(&h);  // the reference byte swap
  const LabelImage a = label_image_from_bytes(n1, "le", kLimit);
  const LabelImage b = label_image_from_bytes(test::nifti2_file(h, test::nifti1_voxels(n1)), "be", kLimit);
  expect_same_grid_exactly(a.grid, b.grid);
  EXPECT_EQ(a.voxels, b.voxels);
}

class BadNifti2 : public ::testing::Test {
 protected:
  std::string n1 = scalar_image_to_bytes(ramp(oblique_grid()), VoxelType::float32, false);
  nifti_2_header h = test::nifti2_header_of(n1);
  std::string voxels{test::nifti1_voxels(n1)};
  ImageF read(const nifti_2_header& hdr, std::size_t limit = kLimit) const {
    return scalar_image_from_bytes(test::nifti2_file(hdr, voxels), "bad2.nii", limit);
  }
};

TEST_F(BadNifti2, MagicDamagedByATextModeTransfer) {
  h.magic[4] = '\n';  // CR/LF rewriting
  expect_refused([&] { read(h); }, "NIfTI-2 magic is damaged");
  h = test::nifti2_header_of(n1);
  h.magic[4] = h.magic[5] = h.magic[6] = h.magic[7] = '\0';  // as niftilib's converter leaves them
  EXPECT_NO_THROW(read(h));
  h.magic[2] = '3';
  expect_refused([&] { read(h); }, "not a NIfTI-2 file (bad magic)");
  std::memcpy(h.magic, "ni2\0", 4);
  expect_refused([&] { read(h); }, "two-file NIfTI-2");
}

TEST_F(BadNifti2, TruncatedHeaderAndData) {
  const std::string file = test::nifti2_file(h, voxels);
  expect_refused([&] { scalar_image_from_bytes(file.substr(0, 400), "cut.nii", kLimit); },
                 "truncated NIfTI-2 header: only 400 bytes");
  expect_refused([&] { scalar_image_from_bytes(test::gzip(file.substr(0, file.size() - 8)), "cut.nii.gz", kLimit); },
                 "truncated");
}

TEST_F(BadNifti2, BadDimsAndOffsets) {
  nifti_2_header bad = h;
  bad.dim[2] = -5;
  expect_refused([&] { read(bad); }, "zero-sized or negative dimension dim[2] = -5");
  bad = h;
  bad.dim[1] = std::int64_t{INT_MAX} + 1;  // fits int64, not a Grid3 axis
  expect_refused([&] { read(bad, std::numeric_limits<std::size_t>::max()); }, "larger than this reader supports");
  bad = h;
  bad.dim[1] = bad.dim[2] = bad.dim[3] = 100000;  // 4e15 bytes: refused before any allocation
  expect_refused([&] { read(bad); }, "more than the limit");
  bad = h;
  bad.vox_offset = 400;  // inside the 540-byte header
  expect_refused([&] { read(bad); }, "invalid vox_offset 400");
  bad = h;
  bad.datatype = 128;  // RGB24
  expect_refused([&] { read(bad); }, "unsupported NIfTI datatype 128");
}

TEST_F(BadNifti2, NonFiniteOrSingularGeometry) {
  nifti_2_header bad = h;
  bad.srow_y[3] = std::numeric_limits<double>::infinity();
  expect_refused([&] { read(bad); }, "NaN/Inf");
  bad = h;
  for (int c = 0; c < 3; ++c) bad.srow_z[c] = bad.srow_x[c];  // two parallel voxel axes
  expect_refused([&] { read(bad); }, "singular");
  bad = h;
  bad.srow_x[0] = 1e3;  // a 1 m voxel
  expect_refused([&] { read(bad); }, "outside [0.01, 100] mm");
}

}  // namespace
}  // namespace brainshift
