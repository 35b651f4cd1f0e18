#pragma once
// What `brainshift pull` writes for a received result frame: the file name and
// bytes `brainshift register --out` would have written. The daemon sends
// images as plain NIfTI (compressing a 47 MB field cost it ~1.5 s of latency),
// so the client gzips them here, where it no longer delays the field.
#include <string>
#include <string_view>

#include "protocol/message.h"

namespace brainshift::cli {

struct PulledFile {
  std::string name;   // relative to the output folder, e.g. "field.nii.gz"; "" = unknown frame
  std::string bytes;  // the file's contents
};

// Gzips a plain-NIfTI frame bound for a .nii.gz name; passes everything else
// through unchanged. Throws std::runtime_error if zlib fails.
PulledFile pulled_file_for(const protocol::Frame& frame);

}  // namespace brainshift::cli
