#pragma once
// One gzip member (RFC 1952) of a byte string, readable by zlib's gzread,
// niftilib and ITK: the engine's .nii.gz and NRRD writers and the
// engine-free client's `pull` share this (a library of its own that needs
// only zlib, so the client links no engine).
#include <string>
#include <string_view>

namespace brainshift {

// level 1 (fastest) by default: a result waits for it, its size matters less.
// ComputeError (a std::runtime_error) if zlib fails.
std::string gzip_bytes(std::string_view bytes, int level = 1);

}  // namespace brainshift
