#pragma once
// What the parts of ServerCore share (server_core.cpp, request_handlers.cpp,
// job_runner.cpp, crash_recovery.cpp): the jobs' types and two helpers.
// Not for use outside ServerCore.
#include <chrono>
#include <map>
#include <optional>
#include <string>

#include "server/server_core.h"

namespace brainshift::server {

using Clock = std::chrono::steady_clock;

inline double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// A fresh preop id from the UTC time and a random suffix.
std::string new_preop_id();

struct ServerCore::PreopJob {
  std::string preop_id;
  std::string source;  // "atlas", "files", "upload", "store"
  std::optional<PreopImages> images;  // absent: build the atlas / read files on the engine thread
  std::string label_table_json;  // the label map as received, stored with the preop
  std::optional<std::string> patient_id;  // preop.load's, normalised; none for the atlas or when not given
  std::shared_ptr<const protocol::LabelMap> label_map;  // parsed once; null when none
  std::optional<TetMesh> stored_mesh;
};

struct ServerCore::DecodedScan {
  std::optional<LabelImage> labels;  // absent: the engine segments the image
  std::optional<ImageF> image;
  double read_seconds = 0.0;
  std::optional<GivenLabelsUse> labels_use;  // the push's; unset: the configuration's
};

// A result between publish_result and write_result: the record as it will
// be stored (state done) and the files the engine made.
struct ServerCore::UnwrittenResult {
  ScanRecord record;
  std::map<std::string, std::string> files;
};

}  // namespace brainshift::server
