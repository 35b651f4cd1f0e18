#pragma once
// Byte payloads for protocol tests: a minimal but well-formed NIfTI-1 file
// (348-byte header, magic "n+1", data at offset 352) whose voxels include NUL
// bytes, so that any text-based handling of frames would corrupt them.
#include <cstdint>
#include <cstring>
#include <string>

#include "protocol/error_codes.h"

namespace brainshift::protocol::testing {

inline std::string fake_nifti(int nx, int ny, int nz) {
  std::string bytes(352 + static_cast<std::size_t>(nx) * ny * nz, '\0');
  const std::int32_t sizeof_hdr = 348;
  std::memcpy(bytes.data(), &sizeof_hdr, 4);
  const std::int16_t dim[8] = {3, static_cast<std::int16_t>(nx), static_cast<std::int16_t>(ny),
                               static_cast<std::int16_t>(nz), 1, 1, 1, 1};
  std::memcpy(bytes.data() + 40, dim, sizeof dim);
  const std::int16_t datatype = 2, bitpix = 8;  // uint8 labels
  std::memcpy(bytes.data() + 70, &datatype, 2);
  std::memcpy(bytes.data() + 72, &bitpix, 2);
  const float vox_offset = 352.0f;
  std::memcpy(bytes.data() + 108, &vox_offset, 4);
  std::memcpy(bytes.data() + 344, "n+1\0", 4);
  for (std::size_t i = 352; i < bytes.size(); ++i) bytes[i] = static_cast<char>(i % 5);  // 0..4
  return bytes;
}

// Starts with the gzip magic; the protocol only checks the magic, not the stream.
inline std::string fake_gzip(std::size_t n) {
  std::string bytes(n, '\0');
  bytes[0] = '\x1f';
  bytes[1] = '\x8b';
  bytes[2] = '\x08';
  return bytes;
}

inline std::string fake_vtp() {
  return "<?xml version=\"1.0\"?>\n<VTKFile type=\"PolyData\" version=\"1.0\">"
         "<PolyData></PolyData></VTKFile>\n";
}

inline std::string fake_h5() {
  std::string bytes("\x89HDF\r\n\x1a\n", 8);
  bytes.append(64, '\0');
  return bytes;
}

// The code of the ProtocolError that fn throws; kInternal when it throws
// nothing (no check here expects kInternal, so it stands for "accepted").
template <class Fn>
ErrorCode error_of(Fn fn) {
  try {
    fn();
  } catch (const ProtocolError& e) {
    return e.code();
  }
  return ErrorCode::kInternal;
}

}  // namespace brainshift::protocol::testing
