#pragma once
// The commands of `brainshift` that talk to brainshiftd: status, load-preop,
// push, pull, list, watch, shutdown; and keygen, which makes CURVE keys.
#include <CLI/CLI.hpp>

#include <functional>
#include <string>
#include <vector>

#include "connection.h"
#include "dicom_nifti.h"

namespace brainshift::cli {

struct NetworkOptions {
  std::string server = "tcp://127.0.0.1:5555";
  std::string events = "tcp://127.0.0.1:5556";
  double timeout_s = 10.0;  // per request
  // CURVE (PROTOCOL.md section 13): both or neither.
  std::string key_prefix;       // this client's PREFIX.key / PREFIX.key_secret
  std::string server_key_file;  // the server's public key file
  // `push --dicom DIR [--series UID]`: the series as NIfTI bytes (the wire
  // stays NIfTI). Set by brainshift-offline (DCMTK is linked there); the
  // engine-free brainshift hands such a push to it.
  std::function<DicomNifti(const std::string& dir, const std::string& series_uid)> dicom_nifti;
  // `push` of .nrrd/.nhdr files (labels: a label map or Slicer .seg.nrrd), likewise.
  std::function<std::string(const std::string& path, bool labels)> nrrd_nifti;
  // `pull --format nrrd`: NRRD copies of the pulled images and field.
  std::function<void(const std::string& out_dir)> nrrd_outputs;
};

// The CURVE keys the options name (nullopt: plain TCP). Throws
// CommandError(kExitUsage) for a missing, malformed or too open key file.
CurveKeys curve_keys(const NetworkOptions& options);

void add_network_commands(CLI::App& app, NetworkOptions& options, int* exit_code);

}  // namespace brainshift::cli
