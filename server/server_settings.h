#pragma once
// brainshiftd's own settings: the [server] section of the same TOML file that
// holds the pipeline parameters (config/brainshiftd.toml). The pipeline
// sections are read by config/; this reads only [server] and ignores the rest.
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "server/roles.h"

namespace brainshift::server {

// What to warm up when the store holds no preop yet.
struct DefaultPreop {
  enum class Kind { none, atlas, files };
  Kind kind = Kind::atlas;
  std::filesystem::path t1;           // files only
  std::filesystem::path labels;       // files only
  std::filesystem::path label_table;  // files only, optional (protocol JSON)
  std::optional<std::string> patient_id;  // files only, optional: as preop.load's (PROTOCOL.md 5.2)
};

// One allowed client key (PROTOCOL.md section 13).
struct AllowedClient {
  std::string name;        // for the log, e.g. "or1-scanner"
  Role role = Role::viewer;
  std::string public_z85;  // the client's CURVE public key, 40 Z85 characters
};

// [security]: CURVE on both sockets, the server's key pair and the allow-list.
// Key file paths are relative to the configuration file's folder.
struct SecuritySettings {
  bool curve = false;
  std::filesystem::path server_secret_key_file;  // required with curve; mode 0600
  std::filesystem::path server_public_key_file;  // optional: checked against the secret key
  std::filesystem::path clients_file;            // optional TOML file of [[clients]] entries
  std::vector<AllowedClient> clients;            // inline [[security.clients]]
  // Without CURVE (loopback only) every client acts as admin except for
  // shutdown, unless this is set.
  bool allow_unauthenticated_shutdown = false;
};

// [openigtlink]: the OpenIGTLink gateway that streams each result to 3D
// Slicer (server/igtl_gateway.h, PROTOCOL.md section 16). OpenIGTLink has no
// authentication or encryption, so it is off unless asked for and listens on
// loopback unless a non-loopback address is allowed explicitly.
struct OpenIgtlinkSettings {
  bool enabled = false;
  int port = 18944;                  // OpenIGTLink's registered port; 0: any free port (tests)
  std::string bind = "127.0.0.1";    // IPv4 address to listen on
  bool allow_non_loopback = false;   // required for a bind outside 127.0.0.0/8
  std::size_t queue_messages = 32;   // per client; beyond it the oldest unsent message is dropped
  std::size_t max_clients = 8;       // connections beyond it are closed at once
  bool push = true;                  // results sent unasked; false: only after a client's STT_ (queries always)
};

struct ServerSettings {
  std::string endpoint = "tcp://127.0.0.1:5555";  // ROUTER, requests
  std::string events = "tcp://127.0.0.1:5556";    // PUB, events and timings
  std::filesystem::path store = "brainshift-store";
  std::size_t queue_depth = 4;  // scans waiting beyond the running one
  // After this long without a job, free heap pages go back to the system
  // (malloc_trim). During a burst of scans the engine keeps its buffers warm
  // (no page zeroing per scan); between scans, minutes apart in the operating
  // room, the daemon holds only what it uses. 0: never.
  std::int64_t idle_release_ms = 30000;
  std::size_t max_frame_bytes = std::size_t{256} << 20;
  std::filesystem::path timing_log;  // relative: inside the store; empty: <store>/timing.jsonl
  DefaultPreop preop;
  std::filesystem::path atlas_cache;  // relative to the working directory; empty: <store>/atlas-cache
  // Plain (unauthenticated, unencrypted) TCP is allowed on loopback only,
  // unless this is set: a hospital network is not a trusted one.
  bool allow_plain_tcp_non_loopback = false;
  SecuritySettings security;
  OpenIgtlinkSettings openigtlink;

  std::filesystem::path timing_log_path() const;
  std::filesystem::path atlas_cache_path() const;
};

// Reads [server], [security] and [openigtlink] from TOML text (missing section or keys:
// defaults). Throws InputError naming source_name and the key for a parse
// error, an unknown key, a wrong type or an out-of-range value. Relative key
// file paths are resolved against base_dir (the configuration file's folder).
ServerSettings server_settings_from_text(const std::string& toml_text,
                                         const std::string& source_name,
                                         const std::filesystem::path& base_dir = {});
ServerSettings server_settings_from_file(const std::filesystem::path& path);

// Throws InputError when an endpoint is malformed, or is not loopback while
// CURVE is off and allow_plain_tcp_non_loopback is not set, or when CURVE is
// on without a server key or an allow-list, or when [openigtlink] bind is
// not an IPv4 address, or not loopback without allow_non_loopback. Reads no
// file (see load_server_curve for the keys themselves).
void validate_endpoints(const ServerSettings& settings);

// tcp://127.0.0.1:..., tcp://localhost:..., tcp://[::1]:..., ipc://, inproc://.
bool is_local_endpoint(const std::string& endpoint);
// A dotted IPv4 address in 127.0.0.0/8.
bool is_loopback_ipv4(const std::string& address);

// An allow-list file: [[clients]] tables {name, role, public_key}, nothing
// else. Throws InputError for a missing or malformed field.
std::vector<AllowedClient> allowed_clients_from_text(const std::string& toml_text, const std::string& source_name);
std::vector<AllowedClient> allowed_clients_from_file(const std::filesystem::path& path);

}  // namespace brainshift::server
