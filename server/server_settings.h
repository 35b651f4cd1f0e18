#pragma once
// brainshiftd's own settings: the [server] section of the same TOML file that
// holds the pipeline parameters (config/brainshiftd.toml). The pipeline
// sections are read by config/; this reads only [server] and ignores the rest.
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>

namespace brainshift::server {

// What to warm up when the store holds no preop yet.
struct DefaultPreop {
  enum class Kind { none, atlas, files };
  Kind kind = Kind::atlas;
  std::filesystem::path t1;           // files only
  std::filesystem::path labels;       // files only
  std::filesystem::path label_table;  // files only, optional (protocol JSON)
};

struct ServerSettings {
  std::string endpoint = "tcp://127.0.0.1:5555";  // ROUTER, requests
  std::string events = "tcp://127.0.0.1:5556";    // PUB, events and timings
  std::filesystem::path store = "brainshift-store";
  std::size_t queue_depth = 4;  // scans waiting beyond the running one
  std::size_t max_frame_bytes = std::size_t{256} << 20;
  std::filesystem::path timing_log;  // relative: inside the store; empty: <store>/timing.jsonl
  DefaultPreop preop;
  std::filesystem::path atlas_cache;  // relative to the working directory; empty: <store>/atlas-cache
  // Plain (unauthenticated, unencrypted) TCP is allowed on loopback only,
  // unless this is set: a hospital network is not a trusted one.
  bool allow_plain_tcp_non_loopback = false;

  std::filesystem::path timing_log_path() const;
  std::filesystem::path atlas_cache_path() const;
};

// Reads [server] from TOML text (missing section or keys: defaults). Throws
// InputError naming source_name and the key for a parse error, an unknown key,
// a wrong type or an out-of-range value.
ServerSettings server_settings_from_text(const std::string& toml_text,
                                         const std::string& source_name);
ServerSettings server_settings_from_file(const std::filesystem::path& path);

// Throws InputError when an endpoint is malformed or is plain TCP on a
// non-loopback address while that is not allowed.
void validate_endpoints(const ServerSettings& settings);

// tcp://127.0.0.1:..., tcp://localhost:..., tcp://[::1]:..., ipc://, inproc://.
bool is_local_endpoint(const std::string& endpoint);

}  // namespace brainshift::server
