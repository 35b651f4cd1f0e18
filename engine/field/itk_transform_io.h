#pragma once
// The pull-back field as an ITK displacement-field transform in HDF5 (.h5), the
// format 3D Slicer and ITK (itk::HDF5TransformIO) load as a transform.
//
// Layout (checked against ITK's itkHDF5TransformIO.cxx and
// itkDisplacementFieldTransform.hxx):
//   /ITKVersion, /HDFVersion, /OSName, /OSVersion   variable-length strings
//   /TransformGroup/0/TransformType                  "DisplacementFieldTransform_double_3_3"
//                                                    (or _float_3_3), variable-length string
//   /TransformGroup/0/TransformFixedParameters       18 doubles: size[3], origin[3],
//                                                    spacing[3], direction[3][3] row-major
//   /TransformGroup/0/TransformParameters            3*N values, vectors interleaved,
//                                                    voxel x fastest
// Geometry and vectors are LPS in the file (ITK's frame) and RAS in memory; the
// conversion is field/lps.h. Direction of the transform: ITK's displacement-field
// transform maps a fixed-image (output) point x to x + u(x) in the moving image,
// which is exactly our pull-back (intraop -> preop), so Slicer resamples the
// preop image into the intraop frame with it without inversion.
// The file is written in the HDF5 1.8 format (as ITK does) for older readers.
#include <filesystem>
#include <string>
#include <string_view>

#include "core/image.h"

namespace brainshift {

struct ItkTransformWriteOptions {
  // float parameters halve the file (ITK reads both; Slicer converts).
  bool single_precision = false;
  // zlib level 0..9 for the parameters (0 = none; compression costs seconds on
  // a 256x256x60 field, so it is off by default).
  int deflate_level = 0;
};

// Throws InputError when the field is empty or inconsistent, and when the
// file cannot be written (message names the file).
void write_itk_displacement_transform(const std::filesystem::path& path,
                                      const VectorImage3& pullback_ras,
                                      const ItkTransformWriteOptions& options = {});
// The same file as bytes (HDF5 core driver, no temporary file).
std::string itk_displacement_transform_bytes(const VectorImage3& pullback_ras,
                                             const ItkTransformWriteOptions& options = {});

// Reads a single displacement-field transform written by ITK, Slicer or the
// writer above (also the old misspelled "TranformParameters" names ITK accepts).
// InputError naming the file for anything else.
VectorImage3 read_itk_displacement_transform(const std::filesystem::path& path);
VectorImage3 itk_displacement_transform_from_bytes(std::string_view bytes, std::string_view name);

}  // namespace brainshift
