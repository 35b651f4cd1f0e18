#pragma once
// Helpers to build NIfTI byte streams with deliberate defects.
#include <nifti/nifti2.h>

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <string>
#include <string_view>

namespace brainshift::test {

std::string gzip(const std::string& raw);
std::string gunzip(const std::string& gz);
void write_bytes(const std::filesystem::path& path, const std::string& bytes);

// Overwrites a value at a byte offset of an uncompressed NIfTI-1 header
// (offsets from the NIfTI-1 specification; the writer is little-endian).
template <class T>
void poke(std::string& bytes, std::size_t offset, T value) {
  std::memcpy(bytes.data() + offset, &value, sizeof(T));
}

namespace offsets {
constexpr std::size_t dim = 40;          // int16[8]
constexpr std::size_t intent_code = 68;  // int16
constexpr std::size_t datatype = 70;     // int16
constexpr std::size_t bitpix = 72;       // int16
constexpr std::size_t pixdim = 76;       // float[8]
constexpr std::size_t vox_offset = 108;  // float
constexpr std::size_t scl_slope = 112;   // float
constexpr std::size_t scl_inter = 116;   // float
constexpr std::size_t qform_code = 252;  // int16
constexpr std::size_t sform_code = 254;  // int16
constexpr std::size_t srow_x = 280;      // float[4]
constexpr std::size_t data = 352;
}  // namespace offsets

// The NIfTI-2 header niftilib makes from the header of an uncompressed
// little-endian NIfTI-1 file (as our writer makes it), with magic
// "n+2\0\r\n\032\n" and vox_offset 544.
nifti_2_header nifti2_header_of(const std::string& nifti1_raw);
// The voxel bytes of an uncompressed NIfTI-1 file (from its vox_offset on).
std::string_view nifti1_voxels(const std::string& nifti1_raw);
// A single-file NIfTI-2: header, the 4-byte extension flag, voxels.
std::string nifti2_file(const nifti_2_header& h, std::string_view voxels);

}  // namespace brainshift::test
