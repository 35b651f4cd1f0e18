#pragma once
// Reading a whole file into memory: the one copy for the engine's readers
// (NIfTI, NRRD, VTK), config/ and the daemon's settings, and the client.
// Header-only, so the engine-free client uses it without linking the engine.
// (The CURVE key files keep the protocol's own bounded reader: the protocol
// links no engine code, and a key file's size is checked before reading.)
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <string_view>

#include "core/errors.h"

namespace brainshift {

// The file's bytes. InputError "<path>: cannot open the <what>" (naming a
// missing file or a directory as such) or "<path>: read error in the <what>".
inline std::string read_whole_file(const std::filesystem::path& path, std::string_view what = "file") {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec))
    throw InputError(path.string() + ": cannot open the " + std::string(what) + " (not found, or not a regular file)");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path.string() + ": cannot open the " + std::string(what));
  std::ostringstream bytes;
  bytes << in.rdbuf();
  if (in.bad()) throw InputError(path.string() + ": read error in the " + std::string(what));
  return std::move(bytes).str();
}

}  // namespace brainshift
