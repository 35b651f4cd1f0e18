#pragma once
// `brainshift push --dicom DIR`: the DICOM series read (engine/image/
// dicom_series.h) and encoded as the gzip NIfTI the protocol carries, in
// memory. Linked into brainshift-offline only (DCMTK).
#include <string>

namespace brainshift::cli {

// Throws InputError (naming the folder) for anything the reader refuses.
std::string dicom_series_nifti(const std::string& dir, const std::string& series_uid);

}  // namespace brainshift::cli
