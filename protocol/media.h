#pragma once
// Media types of binary frames and a cheap content check (magic numbers only,
// no decompression) so that a scanner sending the wrong file is told at once
// instead of failing minutes later inside the pipeline.
#include <string>
#include <string_view>

#include "protocol/message.h"

namespace brainshift::protocol::media {

inline constexpr std::string_view kNifti = "application/x-nifti-1";          // .nii
inline constexpr std::string_view kNiftiGz = "application/x-nifti-1+gzip";   // .nii.gz
inline constexpr std::string_view kItkH5 = "application/x-itk-transform+hdf5";  // .h5
inline constexpr std::string_view kVtp = "application/x-vtk-polydata+xml";   // .vtp
inline constexpr std::string_view kJson = "application/json";
inline constexpr std::string_view kPng = "image/png";                         // report.png

bool is_nifti(std::string_view media_type);

// The NIfTI media type the bytes have (gzip magic or not), and a frame with it.
std::string_view nifti_media_type(std::string_view bytes);
Frame nifti_frame(std::string name, std::string bytes);
Frame json_frame(std::string name, std::string text);

// Throws ProtocolError(kInvalidRequest) when the bytes cannot be what
// frame.media_type says: gzip magic for +gzip, NIfTI-1 header size and magic
// for plain NIfTI, the HDF5 signature, a VTKFile PolyData element, valid JSON,
// the PNG signature.
// Unknown media types are refused: every frame of this protocol has a known one.
void check_content(const Frame& frame);

}  // namespace brainshift::protocol::media
