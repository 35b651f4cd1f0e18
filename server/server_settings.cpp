#include "server/server_settings.h"

#include <arpa/inet.h>

#include "config/toml_reader.h"
#include "core/errors.h"
#include "core/file_bytes.h"
#include "protocol/curve_keys.h"
#include "protocol/fields.h"

namespace brainshift::server {
namespace {

namespace fs = std::filesystem;
using config::TomlSection;

// preop = "atlas" | "none" | { t1 = "...", labels = "...", label_table = "...", patient_id = "..." }
DefaultPreop read_preop(TomlSection& server) {
  DefaultPreop p;
  const toml::node* n = server.node("preop");
  if (!n) return p;
  const char* expected = "must be \"atlas\", \"none\" or a table {t1, labels}";
  if (n->is_string()) {
    const std::string v = n->as_string()->get();
    if (v == "atlas") p.kind = DefaultPreop::Kind::atlas;
    else if (v == "none") p.kind = DefaultPreop::Kind::none;
    else server.fail("preop", std::string(expected) + ", got \"" + v + "\"");
    return p;
  }
  if (!n->is_table()) server.fail("preop", expected);
  TomlSection files = server.table("preop");
  p.kind = DefaultPreop::Kind::files;
  p.t1 = files.string("t1", "");
  p.labels = files.string("labels", "");
  p.label_table = files.string("label_table", "");
  if (files.node("patient_id")) {
    p.patient_id = protocol::detail::normalised_patient_id(files.string("patient_id", ""));
    if (!p.patient_id) files.fail("patient_id", std::string("must be ") + protocol::detail::kPatientIdRule);
  }
  files.reject_unknown_keys();
  if (p.t1.empty() || p.labels.empty()) server.fail("preop", "needs both t1 and labels paths");
  return p;
}

// One allow-list entry {name, role, public_key}.
AllowedClient read_allowed_client(TomlSection& entry) {
  auto text = [&](const char* key) {
    const std::string v = entry.string(key, "");
    if (!entry.node(key)) entry.fail(key, "required, a string");
    return v;
  };
  AllowedClient c;
  c.name = text("name");
  if (c.name.empty() || c.name.size() > 64) entry.fail("name", "1..64 characters");
  const auto role = role_from_string(text("role"));
  if (!role) entry.fail("role", "must be \"scanner\", \"viewer\" or \"admin\"");
  c.role = *role;
  c.public_z85 = text("public_key");
  if (!protocol::curve::is_z85_key(c.public_z85))
    entry.fail("public_key", "not a CURVE public key (40 Z85 characters, as in the .key file of brainshift keygen)");
  entry.reject_unknown_keys();
  return c;
}

std::vector<AllowedClient> read_allowed_clients(TomlSection& section) {
  std::vector<AllowedClient> out;
  for (TomlSection& entry : section.tables("clients")) out.push_back(read_allowed_client(entry));
  return out;
}

fs::path resolve(const fs::path& p, const fs::path& base_dir) {
  return p.empty() || p.is_absolute() || base_dir.empty() ? p : base_dir / p;
}

SecuritySettings read_security(TomlSection& root, const fs::path& base_dir) {
  TomlSection t = root.table("security");
  SecuritySettings s;
  s.curve = t.boolean("curve", false);
  s.allow_unauthenticated_shutdown = t.boolean("allow_unauthenticated_shutdown", false);
  // Key file paths, relative to the configuration file's folder.
  auto path = [&](const char* key) { return resolve(t.string(key, ""), base_dir); };
  s.server_secret_key_file = path("server_secret_key_file");
  s.server_public_key_file = path("server_public_key_file");
  s.clients_file = path("clients_file");
  s.clients = read_allowed_clients(t);
  t.reject_unknown_keys();
  return s;
}

OpenIgtlinkSettings read_openigtlink(TomlSection& root) {
  TomlSection t = root.table("openigtlink");
  OpenIgtlinkSettings o;
  t.read("enabled", o.enabled);
  t.read("port", o.port, 0, 65535);
  t.read("bind", o.bind);
  t.read("allow_non_loopback", o.allow_non_loopback);
  // At least one whole result (three images, four models, a status) fits.
  t.read("queue_messages", o.queue_messages, 8, 1024);
  t.read("max_clients", o.max_clients, 1, 64);
  t.read("push", o.push);
  t.reject_unknown_keys();
  return o;
}

void read_server(TomlSection& root, ServerSettings& s) {
  TomlSection t = root.table("server");
  t.read("endpoint", s.endpoint);
  t.read("events", s.events);
  s.store = t.string("store", s.store.string());
  if (s.store.empty()) t.fail("store", "must not be empty");
  t.read("queue_depth", s.queue_depth, 1, 1000);
  // 1 KiB .. 2 GiB: a frame must at least hold a NIfTI header; above 2 GiB
  // ZeroMQ and our buffers are not the right tool.
  t.read("max_frame_bytes", s.max_frame_bytes, 1024, std::int64_t{2} << 30);
  s.timing_log = t.string("timing_log", "");
  s.atlas_cache = t.string("atlas_cache", "");
  s.preop = read_preop(t);
  t.read("allow_plain_tcp_non_loopback", s.allow_plain_tcp_non_loopback);
  t.read("idle_release_ms", s.idle_release_ms, 0, std::int64_t{24} * 3600 * 1000);  // at most a day
  t.reject_unknown_keys();
}

}  // namespace

std::vector<AllowedClient> allowed_clients_from_text(const std::string& toml_text, const std::string& source) {
  const toml::table document = config::parse_toml(toml_text, source);
  TomlSection root(&document, source, "");
  std::vector<AllowedClient> clients = read_allowed_clients(root);
  root.reject_unknown_keys("unknown key (only [[clients]])");
  return clients;
}

std::vector<AllowedClient> allowed_clients_from_file(const fs::path& path) {
  return allowed_clients_from_text(read_whole_file(path, "client allow-list"), path.string());
}

std::filesystem::path ServerSettings::timing_log_path() const {
  // Relative paths live inside the store, with the case they describe.
  if (timing_log.empty()) return store / "timing.jsonl";
  return timing_log.is_absolute() ? timing_log : store / timing_log;
}
std::filesystem::path ServerSettings::atlas_cache_path() const {
  return atlas_cache.empty() ? store / "atlas-cache" : atlas_cache;
}

ServerSettings server_settings_from_text(const std::string& toml_text, const std::string& source,
                                         const fs::path& base_dir) {
  const toml::table document = config::parse_toml(toml_text, source);
  TomlSection root(&document, source, "");
  ServerSettings s;
  s.security = read_security(root, base_dir);
  s.openigtlink = read_openigtlink(root);
  read_server(root, s);
  return s;
}

ServerSettings server_settings_from_file(const std::filesystem::path& path) {
  return server_settings_from_text(read_whole_file(path, "configuration file"), path.string(), path.parent_path());
}

bool is_loopback_ipv4(const std::string& address) {
  in_addr a{};
  return inet_pton(AF_INET, address.c_str(), &a) == 1 && (ntohl(a.s_addr) >> 24) == 127;
}

bool is_local_endpoint(const std::string& endpoint) {
  if (endpoint.rfind("ipc://", 0) == 0 || endpoint.rfind("inproc://", 0) == 0) return true;
  if (endpoint.rfind("tcp://", 0) != 0) return false;
  const std::string rest = endpoint.substr(6);
  return rest.rfind("127.", 0) == 0 || rest.rfind("localhost:", 0) == 0 ||
         rest.rfind("[::1]:", 0) == 0;
}

void validate_endpoints(const ServerSettings& s) {
  for (const auto& [key, ep] : {std::pair<const char*, const std::string&>{"endpoint", s.endpoint},
                                {"events", s.events}}) {
    const bool known_scheme = ep.rfind("tcp://", 0) == 0 || ep.rfind("ipc://", 0) == 0 ||
                              ep.rfind("inproc://", 0) == 0;
    if (!known_scheme || ep.find("://") + 3 >= ep.size())
      throw InputError(std::string("server.") + key + " \"" + ep +
                       "\": expected tcp://HOST:PORT, ipc://PATH or inproc://NAME");
    if (!is_local_endpoint(ep) && !s.security.curve && !s.allow_plain_tcp_non_loopback)
      throw InputError(std::string("server.") + key + " \"" + ep +
                       "\" is not a loopback address: it requires CURVE ([security] curve = true with the "
                       "server's key and the client allow-list); plain TCP there only with "
                       "[server] allow_plain_tcp_non_loopback = true, on an isolated network");
    if (s.security.curve && ep.rfind("inproc://", 0) == 0)
      throw InputError(std::string("server.") + key + " \"" + ep +
                       "\": CURVE needs a tcp:// or ipc:// endpoint (inproc has no handshake)");
  }
  if (s.security.curve) {
    if (s.security.server_secret_key_file.empty())
      throw InputError("[security] curve = true needs server_secret_key_file (make one with brainshift keygen)");
    if (s.security.clients.empty() && s.security.clients_file.empty())
      throw InputError("[security] curve = true needs an allow-list ([[security.clients]] or clients_file): "
                       "without one no client could connect");
  }
  const OpenIgtlinkSettings& igtl = s.openigtlink;
  if (igtl.enabled) {
    in_addr a{};
    if (inet_pton(AF_INET, igtl.bind.c_str(), &a) != 1)
      throw InputError("[openigtlink] bind \"" + igtl.bind + "\": expected an IPv4 address such as 127.0.0.1");
    if (!is_loopback_ipv4(igtl.bind) && !igtl.allow_non_loopback)
      throw InputError("[openigtlink] bind \"" + igtl.bind +
                       "\" is not a loopback address: OpenIGTLink has no authentication or encryption, so anyone "
                       "on that network could read every result; set [openigtlink] allow_non_loopback = true to "
                       "do it anyway, on an isolated network");
  }
  // "tcp://127.0.0.1:*" twice is fine: the system picks two free ports.
  const bool wildcard = s.endpoint.find('*') != std::string::npos;
  if (s.endpoint == s.events && !wildcard) throw InputError("server.endpoint and server.events must differ");
}

}  // namespace brainshift::server
