#include "protocol/media.h"

#include <cstdint>
#include <cstring>

#include <nlohmann/json.hpp>

#include "protocol/error_codes.h"

namespace brainshift::protocol::media {
namespace {

bool has_gzip_magic(std::string_view b) {
  return b.size() >= 2 && static_cast<unsigned char>(b[0]) == 0x1f &&
         static_cast<unsigned char>(b[1]) == 0x8b;
}

// Single-file NIfTI: sizeof_hdr 348 (either byte order) with magic "n+1\0" at
// byte 344 and data at vox_offset >= 352 (NIfTI-1), or sizeof_hdr 540 with
// magic "n+2\0" at byte 4 and data at vox_offset >= 544 (NIfTI-2). The full
// header is checked by the engine's reader; this only refuses frames whose
// bytes contradict their media type.
bool has_nifti_header(std::string_view b) {
  if (b.size() < 352) return false;
  std::uint32_t sizeof_hdr = 0;
  std::memcpy(&sizeof_hdr, b.data(), 4);
  const std::uint32_t swapped = __builtin_bswap32(sizeof_hdr);
  if (sizeof_hdr == 348 || swapped == 348) return b.substr(344, 4) == std::string_view("n+1\0", 4);
  if (sizeof_hdr == 540 || swapped == 540) return b.size() >= 544 && b.substr(4, 4) == std::string_view("n+2\0", 4);
  return false;
}

bool has_hdf5_signature(std::string_view b) {
  return b.substr(0, 8) == std::string_view("\x89HDF\r\n\x1a\n", 8);
}

bool looks_like_vtp(std::string_view b) {
  const auto head = b.substr(0, 1024);
  return head.find("<VTKFile") != std::string_view::npos &&
         head.find("PolyData") != std::string_view::npos;
}

[[noreturn]] void refuse(const Frame& f, const std::string& why) {
  throw ProtocolError(ErrorCode::kInvalidRequest,
                      "frame \"" + f.name + "\" (" + f.media_type + "): " + why);
}

}  // namespace

bool is_nifti(std::string_view media_type) {
  return media_type == kNifti || media_type == kNiftiGz;
}

std::string_view nifti_media_type(std::string_view bytes) { return has_gzip_magic(bytes) ? kNiftiGz : kNifti; }

Frame nifti_frame(std::string name, std::string bytes) {
  const auto type = nifti_media_type(bytes);
  return Frame{std::move(name), std::string(type), std::move(bytes)};
}

Frame json_frame(std::string name, std::string text) {
  return Frame{std::move(name), std::string(kJson), std::move(text)};
}

void check_content(const Frame& f) {
  const std::string_view b = f.bytes;
  if (f.media_type == kNiftiGz) {
    if (!has_gzip_magic(b)) refuse(f, "not gzip data (no 1f 8b magic)");
  } else if (f.media_type == kNifti) {
    if (!has_nifti_header(b)) refuse(f, "not a single-file NIfTI-1 or NIfTI-2 (sizeof_hdr 348 with magic n+1, or 540 with n+2)");
  } else if (f.media_type == kItkH5) {
    if (!has_hdf5_signature(b)) refuse(f, "no HDF5 signature");
  } else if (f.media_type == kVtp) {
    if (!looks_like_vtp(b)) refuse(f, "no <VTKFile type=\"PolyData\"> element");
  } else if (f.media_type == kJson) {
    if (!nlohmann::json::accept(b)) refuse(f, "not valid JSON");
  } else if (f.media_type == kPng) {
    if (b.substr(0, 8) != std::string_view("\x89PNG\r\n\x1a\n", 8)) refuse(f, "no PNG signature");
  } else {
    refuse(f, "unknown media type");
  }
}

}  // namespace brainshift::protocol::media
