#include "field/itk_transform_io.h"

#include <hdf5.h>
#include <sys/utsname.h>

#include <array>
#include <atomic>
#include <cmath>
#include <vector>

#include "core/errors.h"
#include "field/lps.h"
#include "image/nifti_io.h"

namespace brainshift {
namespace {

constexpr const char* kGroup = "/TransformGroup";
constexpr const char* kTransform = "/TransformGroup/0";
constexpr const char* kType = "/TransformGroup/0/TransformType";
constexpr const char* kFixed = "/TransformGroup/0/TransformFixedParameters";
constexpr const char* kParams = "/TransformGroup/0/TransformParameters";
// Names used by old ITK writers; ITK's reader still falls back to them.
constexpr const char* kFixedOld = "/TransformGroup/0/TranformFixedParameters";
constexpr const char* kParamsOld = "/TransformGroup/0/TranformParameters";

// Owns one HDF5 identifier.
class H5Handle {
 public:
  H5Handle(hid_t id, herr_t (*close)(hid_t)) : id_(id), close_(close) {}
  H5Handle(const H5Handle&) = delete;
  H5Handle& operator=(const H5Handle&) = delete;
  H5Handle(H5Handle&& other) noexcept : id_(other.id_), close_(other.close_) { other.id_ = -1; }
  H5Handle& operator=(H5Handle&&) = delete;
  ~H5Handle() {
    if (id_ >= 0) close_(id_);
  }
  hid_t get() const { return id_; }
  bool ok() const { return id_ >= 0; }

 private:
  hid_t id_;
  herr_t (*close_)(hid_t);
};

// HDF5 prints its error stack to stderr by default; errors become exceptions here.
class QuietHdf5 {
 public:
  QuietHdf5() {
    H5Eget_auto2(H5E_DEFAULT, &func_, &data_);
    H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);
  }
  ~QuietHdf5() { H5Eset_auto2(H5E_DEFAULT, func_, data_); }

 private:
  H5E_auto2_t func_ = nullptr;
  void* data_ = nullptr;
};

void require(bool ok, const std::string& name, const std::string& what) {
  if (!ok) throw InputError(name + ": " + what);
}

// ---------------------------------------------------------------- writing

void write_string(hid_t file, const char* path, const std::string& value, const std::string& name) {
  H5Handle type(H5Tcopy(H5T_C_S1), H5Tclose);
  H5Tset_size(type.get(), H5T_VARIABLE);
  const hsize_t one = 1;
  H5Handle space(H5Screate_simple(1, &one, nullptr), H5Sclose);
  H5Handle set(H5Dcreate2(file, path, type.get(), space.get(), H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT),
               H5Dclose);
  require(set.ok(), name, std::string("cannot create ") + path);
  const char* text = value.c_str();
  require(H5Dwrite(set.get(), type.get(), H5S_ALL, H5S_ALL, H5P_DEFAULT, &text) >= 0, name,
          std::string("cannot write ") + path);
}

void write_doubles(hid_t file, const char* path, const std::vector<double>& values, bool as_float,
                   int deflate_level, const std::string& name) {
  const hsize_t n = values.size();
  H5Handle space(H5Screate_simple(1, &n, nullptr), H5Sclose);
  H5Handle plist(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
  if (deflate_level > 0 && n > 0) {
    const hsize_t chunk = std::min<hsize_t>(n, 1024 * 1024);  // ITK uses 1 M-element chunks
    H5Pset_chunk(plist.get(), 1, &chunk);
    H5Pset_deflate(plist.get(), static_cast<unsigned>(deflate_level));
  }
  const hid_t file_type = as_float ? H5T_IEEE_F32LE : H5T_IEEE_F64LE;
  H5Handle set(H5Dcreate2(file, path, file_type, space.get(), H5P_DEFAULT, plist.get(), H5P_DEFAULT),
               H5Dclose);
  require(set.ok(), name, std::string("cannot create ") + path);
  require(H5Dwrite(set.get(), H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT, values.data()) >= 0,
          name, std::string("cannot write ") + path);
}

// size, origin, spacing, direction (row-major), all LPS.
std::vector<double> fixed_parameters_lps(const Grid3& grid) {
  const Eigen::Matrix4d lps = lps_world_from_ras_world_matrix(grid.world_from_voxel);
  const Eigen::Vector3d spacing = grid.spacing_mm();
  const Eigen::Matrix3d direction = lps.topLeftCorner<3, 3>() * spacing.cwiseInverse().asDiagonal();
  std::vector<double> fixed;
  for (int a = 0; a < 3; ++a) fixed.push_back(grid.dims[a]);
  for (int a = 0; a < 3; ++a) fixed.push_back(lps(a, 3));
  for (int a = 0; a < 3; ++a) fixed.push_back(spacing[a]);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) fixed.push_back(direction(r, c));
  return fixed;
}

std::vector<double> parameters_lps(const VectorImage3& field) {
  std::vector<double> params(3 * field.vectors.size());
  for (std::size_t v = 0; v < field.vectors.size(); ++v) {
    const Eigen::Vector3d lps = ras_to_lps(field.vectors[v].cast<double>());
    params[3 * v] = lps.x();
    params[3 * v + 1] = lps.y();
    params[3 * v + 2] = lps.z();
  }
  return params;
}

std::string os_field(bool release) {
  utsname u{};
  if (uname(&u) != 0) return "unknown";
  return release ? u.release : u.sysname;
}

void write_contents(hid_t file, const VectorImage3& field, const ItkTransformWriteOptions& options,
                    const std::string& name) {
  write_string(file, "/ITKVersion", "brainshift (ITK HDF5TransformIO layout)", name);
  write_string(file, "/HDFVersion", H5_VERS_INFO, name);
  write_string(file, "/OSName", os_field(false), name);
  write_string(file, "/OSVersion", os_field(true), name);
  for (const char* group : {kGroup, kTransform}) {
    H5Handle g(H5Gcreate2(file, group, H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT), H5Gclose);
    require(g.ok(), name, std::string("cannot create group ") + group);
  }
  write_string(file, kType,
               options.single_precision ? "DisplacementFieldTransform_float_3_3"
                                        : "DisplacementFieldTransform_double_3_3",
               name);
  write_doubles(file, kFixed, fixed_parameters_lps(field.grid), false, 0, name);
  write_doubles(file, kParams, parameters_lps(field), options.single_precision, options.deflate_level,
                name);
}

void check_field(const VectorImage3& field, const ItkTransformWriteOptions& options,
                 const std::string& name) {
  require(field.grid.voxel_count() > 0, name, "the displacement field is empty");
  require(field.vectors.size() == field.grid.voxel_count(), name,
          "the displacement field's vector count does not match its grid");
  require(options.deflate_level >= 0 && options.deflate_level <= 9, name,
          "deflate_level must be 0..9");
  validate_world_from_voxel(field.grid.world_from_voxel, name);
}

// Files match ITK: the 1.8 file format, readable by older HDF5 builds.
// In-memory images keep the library's default (earliest) format: with 1.8
// bounds, HDF5 1.10.8's H5Fget_file_image returned an image of a still-open
// file whose superblock checksum does not verify on reopening (measured).
H5Handle file_access(bool in_memory) {
  H5Handle fapl(H5Pcreate(H5P_FILE_ACCESS), H5Pclose);
  if (in_memory) {
    H5Pset_fapl_core(fapl.get(), 1 << 22, /*backing_store=*/0);
  } else {
    H5Pset_libver_bounds(fapl.get(), H5F_LIBVER_V18, H5F_LIBVER_V18);
  }
  return fapl;
}

std::string unique_memory_name() {
  static std::atomic<unsigned long> counter{0};
  return "brainshift-itk-transform-" + std::to_string(counter++) + ".h5";
}

// ---------------------------------------------------------------- reading

bool exists(hid_t file, const char* path) {
  // Checking the parent first keeps H5Lexists from failing on a missing group.
  return H5Lexists(file, kGroup, H5P_DEFAULT) > 0 && H5Lexists(file, kTransform, H5P_DEFAULT) > 0 &&
         H5Lexists(file, path, H5P_DEFAULT) > 0;
}

std::string read_string(hid_t file, const char* path, const std::string& name) {
  require(exists(file, path), name, std::string("no ") + path + " (not an ITK transform file)");
  H5Handle set(H5Dopen2(file, path, H5P_DEFAULT), H5Dclose);
  H5Handle file_type(H5Dget_type(set.get()), H5Tclose);
  require(H5Tget_class(file_type.get()) == H5T_STRING, name, std::string(path) + " is not a string");
  H5Handle mem_type(H5Tcopy(H5T_C_S1), H5Tclose);
  if (H5Tis_variable_str(file_type.get()) > 0) {
    H5Tset_size(mem_type.get(), H5T_VARIABLE);
    char* text = nullptr;
    require(H5Dread(set.get(), mem_type.get(), H5S_ALL, H5S_ALL, H5P_DEFAULT, &text) >= 0 && text,
            name, std::string("cannot read ") + path);
    std::string value(text);
    H5free_memory(text);
    return value;
  }
  const std::size_t size = H5Tget_size(file_type.get());
  H5Tset_size(mem_type.get(), size + 1);
  std::vector<char> buffer(size + 1, '\0');
  require(H5Dread(set.get(), mem_type.get(), H5S_ALL, H5S_ALL, H5P_DEFAULT, buffer.data()) >= 0, name,
          std::string("cannot read ") + path);
  return std::string(buffer.data());
}

std::vector<double> read_doubles(hid_t file, const char* path, const char* old_path,
                                 const std::string& name) {
  const char* used = exists(file, path) ? path : old_path;
  require(exists(file, used), name, std::string("no ") + path);
  H5Handle set(H5Dopen2(file, used, H5P_DEFAULT), H5Dclose);
  H5Handle type(H5Dget_type(set.get()), H5Tclose);
  require(H5Tget_class(type.get()) == H5T_FLOAT, name, std::string(used) + " is not floating point");
  H5Handle space(H5Dget_space(set.get()), H5Sclose);
  require(H5Sget_simple_extent_ndims(space.get()) == 1, name, std::string(used) + " is not 1-D");
  hsize_t n = 0;
  H5Sget_simple_extent_dims(space.get(), &n, nullptr);
  std::vector<double> values(n);
  require(n == 0 || H5Dread(set.get(), H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT,
                            values.data()) >= 0,
          name, std::string("cannot read ") + used);
  return values;
}

Grid3 grid_from_fixed(const std::vector<double>& fixed, const std::string& name) {
  require(fixed.size() == 18, name,
          "TransformFixedParameters has " + std::to_string(fixed.size()) + " values, expected 18");
  Grid3 grid;
  Eigen::Matrix4d lps = Eigen::Matrix4d::Identity();
  for (int a = 0; a < 3; ++a) {
    const double n = fixed[a];
    require(std::isfinite(n) && n >= 1 && n <= 1e5 && n == std::floor(n), name,
            "invalid field size in TransformFixedParameters");
    grid.dims[a] = static_cast<int>(n);
    lps(a, 3) = fixed[3 + a];
  }
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) lps(r, c) = fixed[9 + 3 * r + c] * fixed[6 + c];
  grid.world_from_voxel = ras_world_from_lps_world_matrix(lps);
  validate_world_from_voxel(grid.world_from_voxel, name);
  return grid;
}

VectorImage3 read_contents(hid_t file, const std::string& name) {
  const std::string type = read_string(file, kType, name);
  require(type == "DisplacementFieldTransform_double_3_3" || type == "DisplacementFieldTransform_float_3_3",
          name, "transform type is '" + type + "', expected a 3-D DisplacementFieldTransform");
  VectorImage3 field(grid_from_fixed(read_doubles(file, kFixed, kFixedOld, name), name));
  const std::vector<double> params = read_doubles(file, kParams, kParamsOld, name);
  require(params.size() == 3 * field.vectors.size(), name,
          "TransformParameters has " + std::to_string(params.size()) + " values, expected " +
              std::to_string(3 * field.vectors.size()));
  for (std::size_t v = 0; v < field.vectors.size(); ++v) {
    const Eigen::Vector3d lps(params[3 * v], params[3 * v + 1], params[3 * v + 2]);
    require(lps.allFinite(), name, "non-finite displacement at voxel " + std::to_string(v));
    field.vectors[v] = lps_to_ras(lps).cast<float>();
  }
  return field;
}

}  // namespace

void write_itk_displacement_transform(const std::filesystem::path& path, const VectorImage3& pullback_ras,
                                      const ItkTransformWriteOptions& options) {
  const std::string name = path.string();
  check_field(pullback_ras, options, name);
  QuietHdf5 quiet;
  H5Handle fapl = file_access(false);
  H5Handle file(H5Fcreate(name.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, fapl.get()), H5Fclose);
  require(file.ok(), name, "cannot create the file");
  write_contents(file.get(), pullback_ras, options, name);
  require(H5Fflush(file.get(), H5F_SCOPE_GLOBAL) >= 0, name, "cannot flush the file");
}

std::string itk_displacement_transform_bytes(const VectorImage3& pullback_ras,
                                             const ItkTransformWriteOptions& options) {
  const std::string name = "ITK transform (in memory)";
  check_field(pullback_ras, options, name);
  QuietHdf5 quiet;
  H5Handle fapl = file_access(true);
  H5Handle file(H5Fcreate(unique_memory_name().c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, fapl.get()),
                H5Fclose);
  require(file.ok(), name, "cannot create the in-memory file");
  write_contents(file.get(), pullback_ras, options, name);
  require(H5Fflush(file.get(), H5F_SCOPE_GLOBAL) >= 0, name, "cannot flush");
  const ssize_t size = H5Fget_file_image(file.get(), nullptr, 0);
  require(size > 0, name, "cannot size the file image");
  std::string bytes(static_cast<std::size_t>(size), '\0');
  require(H5Fget_file_image(file.get(), bytes.data(), bytes.size()) == size, name,
          "cannot copy the file image");
  return bytes;
}

VectorImage3 read_itk_displacement_transform(const std::filesystem::path& path) {
  const std::string name = path.string();
  require(std::filesystem::exists(path), name, "file not found");
  QuietHdf5 quiet;
  require(H5Fis_hdf5(name.c_str()) > 0, name, "not an HDF5 file");
  H5Handle file(H5Fopen(name.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
  require(file.ok(), name, "cannot open the HDF5 file");
  return read_contents(file.get(), name);
}

VectorImage3 itk_displacement_transform_from_bytes(std::string_view bytes, std::string_view name_view) {
  const std::string name(name_view);
  require(bytes.size() >= 8 && bytes.substr(0, 8) == std::string_view("\x89HDF\r\n\x1a\n", 8), name,
          "not an HDF5 file");
  QuietHdf5 quiet;
  H5Handle fapl(H5Pcreate(H5P_FILE_ACCESS), H5Pclose);
  H5Pset_fapl_core(fapl.get(), 1 << 22, /*backing_store=*/0);
  // HDF5 copies the image, so the caller's buffer is not modified or retained.
  std::string copy(bytes);
  require(H5Pset_file_image(fapl.get(), copy.data(), copy.size()) >= 0, name, "cannot load the bytes");
  H5Handle file(H5Fopen(unique_memory_name().c_str(), H5F_ACC_RDONLY, fapl.get()), H5Fclose);
  require(file.ok(), name, "cannot open the HDF5 image");
  return read_contents(file.get(), name);
}

}  // namespace brainshift
