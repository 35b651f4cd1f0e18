// The DICOM node for the scanner (brainshift-dicom-node, a sidecar so that
// DCMTK's network stack stays out of brainshiftd): accepts C-STORE from the
// AE titles listed in [dicom_node], stages each instance under
// <staging>/<SeriesInstanceUID>/, and once a series has been quiet for
// series_quiet_s seconds, checks it with the DICOM series reader and hands its
// folder to the queue command (brainshift push --dicom). A series touched by
// an association that ends without a release (aborted, peer killed) is
// deleted: nothing half-stored is ever queued (docs/DESIGN.md, "DICOM node").
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

namespace brainshift::server {

struct DicomNodeSettings {
  bool enabled = false;
  std::string ae_title = "BRAINSHIFT";
  std::uint16_t port = 11112;
  std::vector<std::string> allowed_peers;  // calling AE titles; others refused at association
  std::filesystem::path staging;           // <staging>/<series>, then queued/ or rejected/
  double series_quiet_s = 30.0;
  std::vector<std::string> queue_command;  // argv; the series folder is appended
};

// Reads [dicom_node] of a brainshiftd.toml (InputError on a bad key or value).
DicomNodeSettings dicom_node_settings_from_file(const std::filesystem::path& path);
DicomNodeSettings dicom_node_settings_from_text(const std::string& toml_text, const std::string& source,
                                                const std::filesystem::path& base_dir);

// Runs the node until stop() returns true (checked about once a second
// between associations). Returns 0, or throws InputError when the port
// cannot be opened.
void run_dicom_node(const DicomNodeSettings& settings, const std::function<bool()>& stop);

}  // namespace brainshift::server
