#pragma once
// The gzip layer of the NIfTI reader and writer (internal to engine/image).
// Reading is sequential and pulls only what the caller asks for, so the reader
// can bound the decompressed size before it allocates (gzip bombs); the
// stream's CRC-32 is verified to the end. Raw (uncompressed) bytes go through
// the same interface.
#include <zlib.h>

#include <cstddef>
#include <string>
#include <string_view>

namespace brainshift::nifti_detail {

// Sequential reader over raw or gzip-compressed bytes (detected by the gzip
// magic). name is the file/stream name that starts every error message.
class ByteStream {
 public:
  ByteStream(std::string_view bytes, std::string_view name);
  ~ByteStream();
  ByteStream(const ByteStream&) = delete;
  ByteStream& operator=(const ByteStream&) = delete;

  bool is_gzip() const { return gzip_; }

  // Reads up to n bytes into dst; returns how many were available.
  std::size_t read(char* dst, std::size_t n);

  // gzip only: inflates whatever follows the voxel data to the end of the
  // stream. zlib checks a member's CRC-32 and length only when it reaches the
  // member's trailer, so without this a corrupted stream that still inflates
  // would give wrong voxels silently. Trailing bytes count against budget.
  void verify_to_end(std::size_t budget);

 private:
  std::size_t inflate_into(char* dst, std::size_t n);
  void refill();

  std::string_view in_;
  std::string_view name_;
  bool gzip_ = false;
  bool finished_ = false;
  bool ended_ = false;  // the last member reached its trailer (checksum verified)
  std::size_t pos_ = 0;
  std::size_t consumed_ = 0;
  z_stream zs_{};
};

// Writing gzip is core/gzip.h (gzip_bytes), shared with the client.

}  // namespace brainshift::nifti_detail
