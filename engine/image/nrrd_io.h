#pragma once
// NRRD in and out, as 3D Slicer writes and reads it: .nrrd (header and data
// in one file) and .nhdr (detached data file), raw or gzip, either byte order.
// The space must be left-posterior-superior or right-anterior-superior (Slicer
// writes LPS); images come back in the project's world frame, RAS+ mm, through
// engine/field/lps.h. Written files are LPS (Slicer's convention), gzip.
// The header fields are those of the NRRD0004/NRRD0005 format
// (teem's "nrrd" specification); anything the reader does not understand
// (other spaces, non-spatial axes, skips) is refused with an InputError
// naming the file and the field.
#include <cstddef>
#include <filesystem>

#include "core/image.h"
#include "core/label_table.h"

namespace brainshift {

// True for names ending in .nrrd or .nhdr (a .seg.nrrd too).
bool is_nrrd_path(const std::filesystem::path& path);
// True for Slicer segmentations (.seg.nrrd).
bool is_slicer_segmentation_path(const std::filesystem::path& path);

// Any scalar type, as float. max_bytes bounds the decoded voxels.
ImageF read_nrrd_scalar(const std::filesystem::path& path, std::size_t max_bytes);
// Integer values in 0..65535 only.
LabelImage read_nrrd_labels(const std::filesystem::path& path, std::size_t max_bytes);
// A Slicer segmentation (.seg.nrrd): each segment's SegmentN_Name is looked
// up in the label table (name or short name, case ignored, a space or a
// hyphen read as "_": "Corticospinal tract") and its
// SegmentN_LabelValue voxels in layer SegmentN_Layer get that entry's value;
// a segment the table does not name is refused, listing the table's names.
// Overlapping segments (stored in several layers, a leading list axis of at
// most 64): the brain label gives way to any other (it contains them: a
// brain drawn over the ventricles); two other structures overlapping are
// refused, naming them (which one a voxel is decides its material and
// whether it is resected: the site resolves it in the editor).
LabelImage read_slicer_segmentation(const std::filesystem::path& path, const LabelTable& table,
                                    std::size_t max_bytes);

void write_nrrd_scalar(const std::filesystem::path& path, const ImageF& image);
void write_nrrd_labels(const std::filesystem::path& path, const LabelImage& labels);
// The field as a Slicer grid transform: vectors in LPS mm, "displacement
// field type:=resampling" (the pull-back field: intraop point x maps to the
// preop point x + u(x), Slicer's transform "from parent").
void write_nrrd_displacement(const std::filesystem::path& path, const VectorImage3& field_ras_mm);

}  // namespace brainshift
