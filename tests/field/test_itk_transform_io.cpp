// ITK HDF5 displacement-field transform: layout as ITK writes it (read back
// with the HDF5 C API as an independent reader), LPS signs, round trips.
#include <gtest/gtest.h>
#include <hdf5.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "box_mesh.h"
#include "core/errors.h"
#include "field/itk_transform_io.h"
#include "field/lps.h"
#include "temp_dir.h"  // tests/support

namespace brainshift {
namespace {

namespace fs = std::filesystem;

// The test's scratch files, removed when the program ends.
fs::path temp_path(const std::string& name) {
  static const test::TempDir dir("itk");
  return dir / name;
}

VectorImage3 random_field(const Grid3& g, unsigned seed) {
  VectorImage3 f(g);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> d(-10.f, 10.f);
  for (auto& v : f.vectors) v = Eigen::Vector3f(d(rng), d(rng), d(rng));
  return f;
}

std::string read_h5_string(hid_t file, const char* path, bool* variable) {
  const hid_t set = H5Dopen2(file, path, H5P_DEFAULT);
  EXPECT_GE(set, 0) << path;
  const hid_t type = H5Dget_type(set);
  EXPECT_EQ(H5Tget_class(type), H5T_STRING);
  *variable = H5Tis_variable_str(type) > 0;
  const hid_t mem = H5Tcopy(H5T_C_S1);
  H5Tset_size(mem, H5T_VARIABLE);
  char* text = nullptr;
  EXPECT_GE(H5Dread(set, mem, H5S_ALL, H5S_ALL, H5P_DEFAULT, &text), 0);
  std::string value = text ? text : "";
  H5free_memory(text);
  H5Tclose(mem);
  H5Tclose(type);
  H5Dclose(set);
  return value;
}

std::vector<double> read_h5_doubles(hid_t file, const char* path, std::size_t* bytes_per_value) {
  const hid_t set = H5Dopen2(file, path, H5P_DEFAULT);
  EXPECT_GE(set, 0) << path;
  const hid_t type = H5Dget_type(set);
  EXPECT_EQ(H5Tget_class(type), H5T_FLOAT);
  *bytes_per_value = H5Tget_size(type);
  const hid_t space = H5Dget_space(set);
  EXPECT_EQ(H5Sget_simple_extent_ndims(space), 1);
  hsize_t n = 0;
  H5Sget_simple_extent_dims(space, &n, nullptr);
  std::vector<double> values(n);
  H5Dread(set, H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT, values.data());
  H5Sclose(space);
  H5Tclose(type);
  H5Dclose(set);
  return values;
}

TEST(Lps, KnownTranslationAndMatrix) {
  EXPECT_TRUE(ras_to_lps(Eigen::Vector3d(1, 2, 3)).isApprox(Eigen::Vector3d(-1, -2, 3)));
  EXPECT_TRUE(lps_to_ras(ras_to_lps(Eigen::Vector3d(4, -5, 6))).isApprox(Eigen::Vector3d(4, -5, 6)));
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topRightCorner<3, 1>() = Eigen::Vector3d(10, 20, 30);
  const Eigen::Matrix4d lps = lps_world_from_ras_world_matrix(m);
  // Voxel (1,0,0) is at RAS (11,20,30), i.e. LPS (-11,-20,30).
  EXPECT_TRUE((lps * Eigen::Vector4d(1, 0, 0, 1)).isApprox(Eigen::Vector4d(-11, -20, 30, 1)));
  EXPECT_TRUE(ras_world_from_lps_world_matrix(lps).isApprox(m));
}

// The layout ITK's HDF5TransformIO writes, with the LPS conversion visible in
// every number for a known RAS translation field.
TEST(ItkTransform, LayoutAndLpsSignsOfKnownTranslation) {
  Grid3 g;
  g.dims = {3, 4, 5};
  g.world_from_voxel.topLeftCorner<3, 3>() = Eigen::Vector3d(2.0, 1.5, 3.0).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(10, 20, 30);
  VectorImage3 f(g);
  std::fill(f.vectors.begin(), f.vectors.end(), Eigen::Vector3f(1, 2, 3));
  f.vectors[1] = Eigen::Vector3f(-4, 5, -6);  // voxel (1,0,0): checks x-fastest interleaving
  const fs::path path = temp_path("layout.h5");
  write_itk_displacement_transform(path, f);

  const hid_t file = H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT);
  ASSERT_GE(file, 0);
  bool variable = false;
  EXPECT_EQ(read_h5_string(file, "/TransformGroup/0/TransformType", &variable),
            "DisplacementFieldTransform_double_3_3");
  EXPECT_TRUE(variable);
  for (const char* p : {"/ITKVersion", "/HDFVersion", "/OSName", "/OSVersion"}) {
    EXPECT_FALSE(read_h5_string(file, p, &variable).empty()) << p;
    EXPECT_TRUE(variable) << p;
  }
  std::size_t bytes = 0;
  const std::vector<double> fixed = read_h5_doubles(file, "/TransformGroup/0/TransformFixedParameters", &bytes);
  EXPECT_EQ(bytes, 8u);
  const std::vector<double> expected_fixed{3, 4, 5, -10, -20, 30, 2, 1.5, 3, -1, 0, 0, 0, -1, 0, 0, 0, 1};
  ASSERT_EQ(fixed.size(), 18u);
  for (int n = 0; n < 18; ++n) EXPECT_DOUBLE_EQ(fixed[n], expected_fixed[n]) << "fixed parameter " << n;
  const std::vector<double> params = read_h5_doubles(file, "/TransformGroup/0/TransformParameters", &bytes);
  EXPECT_EQ(bytes, 8u);
  ASSERT_EQ(params.size(), 3u * 60);
  EXPECT_DOUBLE_EQ(params[0], -1);
  EXPECT_DOUBLE_EQ(params[1], -2);
  EXPECT_DOUBLE_EQ(params[2], 3);
  EXPECT_DOUBLE_EQ(params[3], 4);
  EXPECT_DOUBLE_EQ(params[4], -5);
  EXPECT_DOUBLE_EQ(params[5], -6);
  H5Fclose(file);

  // ITK's view: physical LPS point of index (1,2,3) = origin + D * diag(s) * idx,
  // which must be our RAS voxel centre with x and y negated.
  Eigen::Matrix3d d;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) d(r, c) = fixed[9 + 3 * r + c];
  const Eigen::Vector3d itk_point = Eigen::Vector3d(fixed[3], fixed[4], fixed[5]) +
                                    d * Eigen::Vector3d(fixed[6], fixed[7], fixed[8]).asDiagonal() *
                                        Eigen::Vector3d(1, 2, 3);
  EXPECT_TRUE(lps_to_ras(itk_point).isApprox(g.world_mm(1, 2, 3)));
}

TEST(ItkTransform, FileRoundTripOnObliqueGrid) {
  const Grid3 g = test::oblique_grid({7, 6, 5}, Eigen::Vector3d(0.94, 0.94, 2.5), Eigen::Vector3d(-3, 8, -40), 0.4);
  const VectorImage3 f = random_field(g, 3);
  const fs::path path = temp_path("roundtrip.h5");
  write_itk_displacement_transform(path, f);
  const VectorImage3 back = read_itk_displacement_transform(path);
  EXPECT_EQ(back.grid.dims, g.dims);
  EXPECT_LT((back.grid.world_from_voxel - g.world_from_voxel).cwiseAbs().maxCoeff(), 1e-9);
  ASSERT_EQ(back.vectors.size(), f.vectors.size());
  for (std::size_t v = 0; v < f.vectors.size(); ++v) ASSERT_EQ(back.vectors[v], f.vectors[v]);
}

TEST(ItkTransform, BytesRoundTripSinglePrecisionCompressed) {
  const Grid3 g = test::oblique_grid({9, 8, 4}, Eigen::Vector3d(1, 1, 2), Eigen::Vector3d(5, 5, 5), -0.2);
  const VectorImage3 f = random_field(g, 11);
  ItkTransformWriteOptions options;
  options.single_precision = true;
  options.deflate_level = 4;
  const std::string bytes = itk_displacement_transform_bytes(f, options);
  const VectorImage3 back = itk_displacement_transform_from_bytes(bytes, "reply");
  EXPECT_EQ(back.grid.dims, g.dims);
  EXPECT_LT((back.grid.world_from_voxel - g.world_from_voxel).cwiseAbs().maxCoeff(), 1e-9);
  for (std::size_t v = 0; v < f.vectors.size(); ++v) ASSERT_EQ(back.vectors[v], f.vectors[v]);
  // The bytes are a complete HDF5 file that the file reader accepts too.
  const fs::path path = temp_path("from_bytes.h5");
  std::ofstream(path, std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  EXPECT_EQ(read_itk_displacement_transform(path).vectors.size(), f.vectors.size());
}

TEST(ItkTransform, BadFilesAreInputErrorsNamingTheFile) {
  const fs::path garbage = temp_path("garbage.h5");
  std::ofstream(garbage) << "this is not HDF5";
  try {
    read_itk_displacement_transform(garbage);
    FAIL() << "garbage accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("garbage.h5"), std::string::npos) << e.what();
  }
  EXPECT_THROW(read_itk_displacement_transform(temp_path("missing.h5")), InputError);
  EXPECT_THROW(itk_displacement_transform_from_bytes("nope", "reply"), InputError);

  // A valid HDF5 file that is not a transform.
  const fs::path empty = temp_path("empty.h5");
  H5Fclose(H5Fcreate(empty.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT));
  EXPECT_THROW(read_itk_displacement_transform(empty), InputError);

  // A transform of another type.
  const fs::path affine = temp_path("affine.h5");
  {
    VectorImage3 f(test::oblique_grid({2, 2, 2}, Eigen::Vector3d(1, 1, 1), Eigen::Vector3d::Zero(), 0));
    write_itk_displacement_transform(affine, f);
    const hid_t file = H5Fopen(affine.c_str(), H5F_ACC_RDWR, H5P_DEFAULT);
    H5Ldelete(file, "/TransformGroup/0/TransformType", H5P_DEFAULT);
    const hid_t type = H5Tcopy(H5T_C_S1);
    H5Tset_size(type, H5T_VARIABLE);
    const hsize_t one = 1;
    const hid_t space = H5Screate_simple(1, &one, nullptr);
    const hid_t set = H5Dcreate2(file, "/TransformGroup/0/TransformType", type, space, H5P_DEFAULT,
                                 H5P_DEFAULT, H5P_DEFAULT);
    const char* text = "AffineTransform_double_3_3";
    H5Dwrite(set, type, H5S_ALL, H5S_ALL, H5P_DEFAULT, &text);
    H5Dclose(set);
    H5Sclose(space);
    H5Tclose(type);
    H5Fclose(file);
  }
  try {
    read_itk_displacement_transform(affine);
    FAIL() << "affine accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("AffineTransform"), std::string::npos) << e.what();
  }
  EXPECT_THROW(write_itk_displacement_transform(temp_path("x.h5"), VectorImage3{}), InputError);
}

}  // namespace
}  // namespace brainshift
