#pragma once
// Thin RAII helpers over the HDF5 C API for the case store.
//
// Debian's HDF5 (Open MPI flavour) is built WITHOUT thread safety, and both the
// socket thread (storing pushed scans) and the engine thread (results, the
// engine's own ITK .h5 writer) use it. Every HDF5 call in the daemon therefore
// runs under hdf5_mutex(); the engine adapter holds it around the engine's
// HDF5 writers too. Result bytes are served with pread() at recorded file
// offsets, so pulls never take this lock.
#include <hdf5.h>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <mutex>
#include <string>
#include <vector>

namespace brainshift::server::h5 {

std::mutex& hdf5_mutex();

// Owns an hid_t and closes it with the right H5*close.
class Handle {
 public:
  enum class Kind { file, group, dataset, dataspace, datatype, attribute, plist };
  Handle() = default;
  Handle(hid_t id, Kind kind);
  ~Handle();
  Handle(Handle&& o) noexcept;
  Handle& operator=(Handle&& o) noexcept;
  Handle(const Handle&) = delete;
  Handle& operator=(const Handle&) = delete;
  hid_t get() const { return id_; }

 private:
  hid_t id_ = H5I_INVALID_HID;
  Kind kind_ = Kind::file;
};

// Throws std::runtime_error naming the file when HDF5 refuses.
Handle create_file(const std::filesystem::path& path);  // truncates
Handle open_file_read(const std::filesystem::path& path);
// A file that lives in memory only (core driver, no backing store). The store
// builds every file this way and writes the image itself: a full disk then
// fails a plain write() the store handles, never an HDF5 close, which left a
// half-closed file that crashed HDF5 at exit (measured with RLIMIT_FSIZE).
// expected_bytes: the payload about to be written, so the buffer is allocated once.
Handle create_in_memory(std::size_t expected_bytes = 0);
// Flushes an in-memory file and returns its bytes.
std::string file_image(hid_t file);

// A contiguous 1-D/N-D dataset. dims outermost first (C order).
void write_dataset(hid_t loc, const std::string& name, hid_t mem_type,
                   const std::vector<hsize_t>& dims, const void* data);
std::vector<hsize_t> dataset_dims(hid_t loc, const std::string& name);
void read_dataset(hid_t loc, const std::string& name, hid_t mem_type, void* data);
bool exists(hid_t loc, const std::string& name);

// Opaque bytes as a contiguous uint8 dataset; returns its file offset (for
// pread) or -1 for an empty dataset.
std::int64_t write_bytes(hid_t loc, const std::string& name, const std::string& bytes);
std::string read_bytes(hid_t loc, const std::string& name);
std::int64_t dataset_offset(hid_t loc, const std::string& name);

// A fixed-length string attribute (JSON metadata, readable with h5dump).
void write_string_attribute(hid_t loc, const std::string& name, const std::string& value);
std::string read_string_attribute(hid_t loc, const std::string& name);

// fsync of a file or directory, so a rename that follows is durable.
void fsync_path(const std::filesystem::path& path);

}  // namespace brainshift::server::h5
