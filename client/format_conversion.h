#pragma once
// The formats the client converts: the inputs `brainshift push` turns into
// the NIfTI the protocol carries, in memory (a DICOM series,
// engine/image/dicom_series.h; NRRD files, Slicer segmentations included,
// engine/image/nrrd_io.h), and `pull --format nrrd`'s NRRD copies of the
// pulled NIfTI files. Linked into brainshift-offline only (DCMTK, the
// engine's readers and writers).
#include <string>

#include "dicom_nifti.h"

namespace brainshift::cli {

// Throws InputError (naming the folder) for anything the reader refuses.
DicomNifti dicom_series_nifti(const std::string& dir, const std::string& series_uid);
// A .nrrd/.nhdr image, or (labels) a label map; a .seg.nrrd's segments are
// mapped by name to the shipped label table (config/labels.toml).
std::string nrrd_nifti(const std::string& path, bool labels);
// DIR's field.nii.gz, warped_image.nii.gz and warped_labels.nii.gz (those
// present) also as field.nrrd (a Slicer grid transform, LPS, "displacement
// field type:=resampling"), warped_image.nrrd and warped_labels.nrrd; prints
// each file written.
void write_nrrd_outputs(const std::string& dir);

}  // namespace brainshift::cli
