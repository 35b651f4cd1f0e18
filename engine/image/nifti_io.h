#pragma once
// NIfTI reading (NIfTI-1 and NIfTI-2, .nii and .nii.gz) and NIfTI-1 writing,
// from files and from in-memory bytes.
//
// Geometry: world_from_voxel maps voxel indices to world RAS+ mm. It is taken
// from the sform when sform_code > 0, else from the qform when qform_code > 0,
// else (old ANALYZE-style files) it is diag(pixdim[1..3]) with no offset.
// NIfTI-2 headers (540 bytes, int64 dims, double sform/qform) read into the
// same image types; their double geometry is kept as it is.
// Writers store the same affine in the sform and, when its 3x3 part is a rotation
// times a positive diagonal scale, also in the qform (both with code
// NIFTI_XFORM_SCANNER_ANAT = 1), so other tools (FSL, ITK, nibabel) agree.
//
// The header layouts are the reference ones (nifti1.h, nifti2.h from Debian's
// libnifti2-dev); the reading itself is ours, because it must bound memory
// before allocating and read from memory (docs/DESIGN.md, "NIfTI I/O").
// Both byte orders are accepted; only single-file NIfTI ("n+1", "n+2").
// Every error is an InputError whose message starts with the file/stream name.
// Sources: nifti_header.cpp (headers, geometry), nifti_read.cpp, nifti_write.cpp,
// nifti_gzip.cpp (bounded inflate, deflate).
#include <cstddef>
#include <filesystem>
#include <string>
#include <string_view>

#include "core/image.h"

namespace brainshift {

// Reads any of u8,i8,u16,i16,u32,i32,i64,u64,f32,f64, applies scl_slope/scl_inter
// (when scl_slope != 0) and returns float. Rejects NaN/Inf voxels.
// max_decompressed_bytes bounds memory as for the in-memory readers below.
ImageF read_scalar_image(const std::filesystem::path& path,
                         std::size_t max_decompressed_bytes = static_cast<std::size_t>(-1));
// Integer-valued data in 0..65535 only (after scl_slope/scl_inter), else InputError.
LabelImage read_label_image(const std::filesystem::path& path,
                            std::size_t max_decompressed_bytes = static_cast<std::size_t>(-1));
// 5-D (nx,ny,nz,1,3) vector field, components planar (dim5 slowest), in mm.
VectorImage3 read_vector_image(const std::filesystem::path& path);

enum class VoxelType { float32, uint8, int16 };

// uint8/int16: integer-valued images that fit the type are stored exactly
// (scl_slope 1); anything else is linearly scaled over the type's range through
// scl_slope/scl_inter (lossy, like other NIfTI writers).
void write_scalar_image(const std::filesystem::path& path, const ImageF& image,
                        VoxelType type = VoxelType::float32);
// uint8 when max <= 255, else int16 (InputError if a label is > 32767).
void write_label_image(const std::filesystem::path& path, const LabelImage& labels);
// float32, dims (nx,ny,nz,1,3), intent_code 1006 (NIFTI_INTENT_DISPVECT).
void write_displacement_field(const std::filesystem::path& path, const VectorImage3& field_mm);

// In-memory variants (the daemon receives/sends NIfTI bytes over sockets).
// bytes may be gzipped (detected by the gzip magic) or raw. name is used in
// error messages. max_decompressed_bytes bounds memory: the header is decoded
// first and vox_offset + nvox * bytes_per_voxel is checked against the bound
// before any voxel buffer is allocated (gzip bombs are refused early).
ImageF scalar_image_from_bytes(std::string_view bytes, std::string_view name,
                               std::size_t max_decompressed_bytes);
LabelImage label_image_from_bytes(std::string_view bytes, std::string_view name,
                                  std::size_t max_decompressed_bytes);
VectorImage3 vector_image_from_bytes(std::string_view bytes, std::string_view name,
                                     std::size_t max_decompressed_bytes);
std::string scalar_image_to_bytes(const ImageF& image, VoxelType type, bool gzip);
std::string label_image_to_bytes(const LabelImage& labels, bool gzip);
std::string displacement_field_to_bytes(const VectorImage3& field_mm, bool gzip);

// Checks a world_from_voxel matrix the way the readers do (finite, invertible,
// last row 0 0 0 1, voxel sizes in [0.01, 100] mm); throws InputError naming `what`.
void validate_world_from_voxel(const Eigen::Matrix4d& world_from_voxel, std::string_view what);

}  // namespace brainshift
