#include "server/hdf5_file.h"

#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <stdexcept>

namespace brainshift::server::h5 {

std::mutex& hdf5_mutex() {
  static std::mutex m;
  return m;
}

namespace {
[[noreturn]] void fail(const std::string& what) { throw std::runtime_error("HDF5: " + what); }

hid_t check(hid_t id, const std::string& what) {
  if (id < 0) fail(what);
  return id;
}
}  // namespace

Handle::Handle(hid_t id, Kind kind) : id_(id), kind_(kind) {}
Handle::~Handle() {
  if (id_ < 0) return;
  switch (kind_) {
    case Kind::file: H5Fclose(id_); break;
    case Kind::group: H5Gclose(id_); break;
    case Kind::dataset: H5Dclose(id_); break;
    case Kind::dataspace: H5Sclose(id_); break;
    case Kind::datatype: H5Tclose(id_); break;
    case Kind::attribute: H5Aclose(id_); break;
    case Kind::plist: H5Pclose(id_); break;
  }
}
Handle::Handle(Handle&& o) noexcept : id_(o.id_), kind_(o.kind_) { o.id_ = H5I_INVALID_HID; }
Handle& Handle::operator=(Handle&& o) noexcept {
  if (this != &o) {
    this->~Handle();
    id_ = o.id_;
    kind_ = o.kind_;
    o.id_ = H5I_INVALID_HID;
  }
  return *this;
}

Handle create_file(const std::filesystem::path& path) {
  // HDF5 prints its error stack to stderr by default; we report errors ourselves.
  H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);
  return Handle(check(H5Fcreate(path.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT),
                      "cannot create " + path.string()),
                Handle::Kind::file);
}

Handle create_in_memory(std::size_t expected_bytes) {
  H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);
  static std::atomic<unsigned long> counter{0};
  const std::string name = "brainshift-store-" + std::to_string(counter++) + ".h5";
  Handle fapl(check(H5Pcreate(H5P_FILE_ACCESS), "plist"), Handle::Kind::plist);
  // Grown in steps of the expected size plus 1 MiB for HDF5's own metadata:
  // one allocation for a result file (growing a 66 MB result in 1 MiB steps
  // copied the buffer over and over: ~0.1 s of a scan's latency), and no
  // rounding up that would add to the daemon's peak memory (the buffer exists
  // beside its copy, file_image, for a moment).
  H5Pset_fapl_core(fapl.get(), expected_bytes + (std::size_t{1} << 20), /*backing_store=*/0);
  return Handle(check(H5Fcreate(name.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, fapl.get()), "cannot create " + name),
                Handle::Kind::file);
}

std::string file_image(hid_t file) {
  if (H5Fflush(file, H5F_SCOPE_GLOBAL) < 0) fail("cannot flush an in-memory file");
  const ssize_t size = H5Fget_file_image(file, nullptr, 0);
  if (size <= 0) fail("cannot size an in-memory file");
  std::string bytes(static_cast<std::size_t>(size), '\0');
  if (H5Fget_file_image(file, bytes.data(), bytes.size()) != size) fail("cannot copy an in-memory file");
  return bytes;
}

Handle open_file_read(const std::filesystem::path& path) {
  H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);
  return Handle(check(H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT),
                      "cannot open " + path.string()),
                Handle::Kind::file);
}

void write_dataset(hid_t loc, const std::string& name, hid_t mem_type,
                   const std::vector<hsize_t>& dims, const void* data) {
  Handle space(check(H5Screate_simple(static_cast<int>(dims.size()), dims.data(), nullptr),
                     "dataspace for " + name),
               Handle::Kind::dataspace);
  // Early allocation gives even a never-written dataset a file address.
  Handle dcpl(check(H5Pcreate(H5P_DATASET_CREATE), "plist"), Handle::Kind::plist);
  H5Pset_layout(dcpl.get(), H5D_CONTIGUOUS);
  H5Pset_alloc_time(dcpl.get(), H5D_ALLOC_TIME_EARLY);
  // Every byte is written right below: filling with zeros first would write
  // the (tens of MB) dataset twice.
  H5Pset_fill_time(dcpl.get(), H5D_FILL_TIME_NEVER);
  Handle lcpl(check(H5Pcreate(H5P_LINK_CREATE), "plist"), Handle::Kind::plist);
  H5Pset_create_intermediate_group(lcpl.get(), 1);
  Handle ds(check(H5Dcreate2(loc, name.c_str(), mem_type, space.get(), lcpl.get(), dcpl.get(),
                             H5P_DEFAULT),
                  "cannot create dataset " + name),
            Handle::Kind::dataset);
  std::size_t count = 1;
  for (hsize_t d : dims) count *= d;
  if (count > 0 && H5Dwrite(ds.get(), mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, data) < 0)
    fail("cannot write dataset " + name);
}

std::vector<hsize_t> dataset_dims(hid_t loc, const std::string& name) {
  Handle ds(check(H5Dopen2(loc, name.c_str(), H5P_DEFAULT), "missing dataset " + name),
            Handle::Kind::dataset);
  Handle space(check(H5Dget_space(ds.get()), "dataspace of " + name), Handle::Kind::dataspace);
  const int rank = H5Sget_simple_extent_ndims(space.get());
  if (rank < 0) fail("bad dataspace of " + name);
  std::vector<hsize_t> dims(static_cast<std::size_t>(rank));
  H5Sget_simple_extent_dims(space.get(), dims.data(), nullptr);
  return dims;
}

void read_dataset(hid_t loc, const std::string& name, hid_t mem_type, void* data) {
  Handle ds(check(H5Dopen2(loc, name.c_str(), H5P_DEFAULT), "missing dataset " + name),
            Handle::Kind::dataset);
  if (H5Dread(ds.get(), mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, data) < 0)
    fail("cannot read dataset " + name);
}

bool exists(hid_t loc, const std::string& name) {
  return H5Lexists(loc, name.c_str(), H5P_DEFAULT) > 0;
}

std::int64_t write_bytes(hid_t loc, const std::string& name, const std::string& bytes) {
  write_dataset(loc, name, H5T_NATIVE_UINT8, {static_cast<hsize_t>(bytes.size())}, bytes.data());
  return bytes.empty() ? -1 : dataset_offset(loc, name);
}

std::string read_bytes(hid_t loc, const std::string& name) {
  const auto dims = dataset_dims(loc, name);
  if (dims.size() != 1) fail(name + " is not a byte array");
  std::string out(dims[0], '\0');
  if (!out.empty()) read_dataset(loc, name, H5T_NATIVE_UINT8, out.data());
  return out;
}

std::int64_t dataset_offset(hid_t loc, const std::string& name) {
  Handle ds(check(H5Dopen2(loc, name.c_str(), H5P_DEFAULT), "missing dataset " + name),
            Handle::Kind::dataset);
  const haddr_t off = H5Dget_offset(ds.get());
  return off == HADDR_UNDEF ? -1 : static_cast<std::int64_t>(off);
}

void write_string_attribute(hid_t loc, const std::string& name, const std::string& value) {
  Handle type(check(H5Tcopy(H5T_C_S1), "string type"), Handle::Kind::datatype);
  H5Tset_size(type.get(), value.empty() ? 1 : value.size());
  H5Tset_strpad(type.get(), H5T_STR_NULLPAD);
  Handle space(check(H5Screate(H5S_SCALAR), "scalar space"), Handle::Kind::dataspace);
  Handle attr(check(H5Acreate2(loc, name.c_str(), type.get(), space.get(), H5P_DEFAULT, H5P_DEFAULT),
                    "cannot create attribute " + name),
              Handle::Kind::attribute);
  const std::string padded = value.empty() ? std::string(1, '\0') : value;
  if (H5Awrite(attr.get(), type.get(), padded.data()) < 0) fail("cannot write attribute " + name);
}

std::string read_string_attribute(hid_t loc, const std::string& name) {
  Handle attr(check(H5Aopen(loc, name.c_str(), H5P_DEFAULT), "missing attribute " + name),
              Handle::Kind::attribute);
  Handle type(check(H5Aget_type(attr.get()), "attribute type"), Handle::Kind::datatype);
  if (H5Tget_class(type.get()) != H5T_STRING || H5Tis_variable_str(type.get()) > 0)
    fail("attribute " + name + " is not a fixed-length string");
  const std::size_t size = H5Tget_size(type.get());
  std::string out(size, '\0');
  if (H5Aread(attr.get(), type.get(), out.data()) < 0) fail("cannot read attribute " + name);
  const auto end = out.find('\0');
  if (end != std::string::npos) out.resize(end);
  return out;
}

void fsync_path(const std::filesystem::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw std::runtime_error("cannot open " + path.string() + " to sync it");
  const int rc = ::fsync(fd);
  ::close(fd);
  if (rc != 0) throw std::runtime_error("fsync failed for " + path.string());
}

}  // namespace brainshift::server::h5
