#pragma once
// A DICOM series converted for the wire (which carries NIfTI only): its
// voxels as NIfTI bytes and its PatientID, which `push` sends as the scan's
// patient_id (PROTOCOL.md, "Patient identity").
#include <string>

namespace brainshift::cli {

struct DicomNifti {
  std::string nifti;
  std::string patient_id;  // (0010,0020) as written; "" when absent
};

}  // namespace brainshift::cli
