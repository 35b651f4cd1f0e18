#include "server/server_settings.h"

#include <arpa/inet.h>

#include <fstream>
#include <set>
#include <sstream>

#include <toml++/toml.h>

#include "core/errors.h"
#include "protocol/curve_keys.h"

namespace brainshift::server {
namespace {

namespace fs = std::filesystem;

[[noreturn]] void fail(const std::string& source, const std::string& key, const std::string& what,
                       const char* section = "server") {
  throw InputError(source + ": [" + section + "] " + key + ": " + what);
}
[[noreturn]] void fail_security(const std::string& source, const std::string& key, const std::string& what) {
  throw InputError(source + ": [security] " + key + ": " + what);
}

std::string get_string(const toml::table& t, const char* key, const std::string& fallback,
                       const std::string& source, const char* section = "server") {
  const toml::node* n = t.get(key);
  if (!n) return fallback;
  if (!n->is_string()) fail(source, key, "must be a string", section);
  return n->as_string()->get();
}

std::int64_t get_int(const toml::table& t, const char* key, std::int64_t fallback,
                     std::int64_t lo, std::int64_t hi, const std::string& source, const char* section = "server") {
  const toml::node* n = t.get(key);
  if (!n) return fallback;
  if (!n->is_integer()) fail(source, key, "must be an integer", section);
  const std::int64_t v = n->as_integer()->get();
  if (v < lo || v > hi)
    fail(source, key, "must be in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got " +
                          std::to_string(v), section);
  return v;
}

bool get_bool(const toml::table& t, const char* key, bool fallback, const std::string& source,
              const char* section = "server") {
  const toml::node* n = t.get(key);
  if (!n) return fallback;
  if (!n->is_boolean()) fail(source, key, "must be true or false", section);
  return n->as_boolean()->get();
}

// preop = "atlas" | "none" | { t1 = "...", labels = "...", label_table = "..." }
DefaultPreop read_preop(const toml::table& t, const std::string& source) {
  DefaultPreop p;
  const toml::node* n = t.get("preop");
  if (!n) return p;
  if (n->is_string()) {
    const std::string v = n->as_string()->get();
    if (v == "atlas") p.kind = DefaultPreop::Kind::atlas;
    else if (v == "none") p.kind = DefaultPreop::Kind::none;
    else fail(source, "preop", "must be \"atlas\", \"none\" or a table {t1, labels}, got \"" + v + "\"");
    return p;
  }
  if (!n->is_table()) fail(source, "preop", "must be \"atlas\", \"none\" or a table {t1, labels}");
  const toml::table& pt = *n->as_table();
  for (const auto& [k, v] : pt) {
    const std::string key(k.str());
    if (key != "t1" && key != "labels" && key != "label_table") fail(source, "preop." + key, "unknown key");
  }
  p.kind = DefaultPreop::Kind::files;
  p.t1 = get_string(pt, "t1", "", source);
  p.labels = get_string(pt, "labels", "", source);
  p.label_table = get_string(pt, "label_table", "", source);
  if (p.t1.empty() || p.labels.empty()) fail(source, "preop", "needs both t1 and labels paths");
  return p;
}

toml::table parse_toml(const std::string& text, const std::string& source) {
  try {
    return toml::parse(text, source);
  } catch (const toml::parse_error& e) {
    std::ostringstream os;
    os << source << ": TOML parse error at line " << e.source().begin.line << ": " << e.description();
    throw InputError(os.str());
  }
}

// One allow-list entry {name, role, public_key}; `where` names it in messages.
AllowedClient read_allowed_client(const toml::node& node, const std::string& where) {
  const toml::table* t = node.as_table();
  if (!t) throw InputError(where + ": must be a table {name, role, public_key}");
  for (const auto& [k, v] : *t) {
    const std::string key(k.str());
    if (key != "name" && key != "role" && key != "public_key") throw InputError(where + "." + key + ": unknown key");
  }
  auto text = [&](const char* key) {
    const toml::node* n = t->get(key);
    if (!n || !n->is_string()) throw InputError(where + "." + key + ": required, a string");
    return n->as_string()->get();
  };
  AllowedClient c;
  c.name = text("name");
  if (c.name.empty() || c.name.size() > 64) throw InputError(where + ".name: 1..64 characters");
  const auto role = role_from_string(text("role"));
  if (!role) throw InputError(where + ".role: must be \"scanner\", \"viewer\" or \"admin\"");
  c.role = *role;
  c.public_z85 = text("public_key");
  if (!protocol::curve::is_z85_key(c.public_z85))
    throw InputError(where + ".public_key: not a CURVE public key (40 Z85 characters, as in the .key file of "
                             "brainshift keygen)");
  return c;
}

std::vector<AllowedClient> read_allowed_clients(const toml::node* n, const std::string& where) {
  std::vector<AllowedClient> out;
  if (!n) return out;
  const toml::array* a = n->as_array();
  if (!a) throw InputError(where + ": must be an array of tables [[...]]");
  for (std::size_t i = 0; i < a->size(); ++i)
    out.push_back(read_allowed_client(*a->get(i), where + "[" + std::to_string(i) + "]"));
  return out;
}

fs::path resolve(const fs::path& p, const fs::path& base_dir) {
  return p.empty() || p.is_absolute() || base_dir.empty() ? p : base_dir / p;
}

SecuritySettings read_security(const toml::node* section, const std::string& source, const fs::path& base_dir) {
  SecuritySettings s;
  if (!section) return s;
  if (!section->is_table()) throw InputError(source + ": [security] must be a table");
  const toml::table& t = *section->as_table();
  static const std::set<std::string> known = {"curve", "server_secret_key_file", "server_public_key_file",
                                              "clients_file", "clients", "allow_unauthenticated_shutdown"};
  for (const auto& [k, v] : t)
    if (!known.count(std::string(k.str()))) fail_security(source, std::string(k.str()), "unknown key");
  auto flag = [&](const char* key, bool fallback) {
    const toml::node* n = t.get(key);
    if (!n) return fallback;
    if (!n->is_boolean()) fail_security(source, key, "must be true or false");
    return n->as_boolean()->get();
  };
  auto path = [&](const char* key) {
    const toml::node* n = t.get(key);
    if (!n) return fs::path();
    if (!n->is_string()) fail_security(source, key, "must be a string (a file path)");
    return resolve(n->as_string()->get(), base_dir);
  };
  s.curve = flag("curve", false);
  s.allow_unauthenticated_shutdown = flag("allow_unauthenticated_shutdown", false);
  s.server_secret_key_file = path("server_secret_key_file");
  s.server_public_key_file = path("server_public_key_file");
  s.clients_file = path("clients_file");
  s.clients = read_allowed_clients(t.get("clients"), source + ": [[security.clients]]");
  return s;
}

OpenIgtlinkSettings read_openigtlink(const toml::node* section, const std::string& source) {
  OpenIgtlinkSettings o;
  if (!section) return o;
  if (!section->is_table()) throw InputError(source + ": [openigtlink] must be a table");
  const toml::table& t = *section->as_table();
  static const std::set<std::string> known = {"enabled", "port", "bind", "allow_non_loopback", "queue_messages",
                                              "max_clients"};
  const char* in = "openigtlink";
  for (const auto& [k, v] : t)
    if (!known.count(std::string(k.str()))) fail(source, std::string(k.str()), "unknown key", in);
  o.enabled = get_bool(t, "enabled", o.enabled, source, in);
  o.port = static_cast<int>(get_int(t, "port", o.port, 0, 65535, source, in));
  o.bind = get_string(t, "bind", o.bind, source, in);
  o.allow_non_loopback = get_bool(t, "allow_non_loopback", o.allow_non_loopback, source, in);
  // At least one whole result (three images, four models, a status) fits.
  o.queue_messages = static_cast<std::size_t>(
      get_int(t, "queue_messages", static_cast<std::int64_t>(o.queue_messages), 8, 1024, source, in));
  o.max_clients = static_cast<std::size_t>(
      get_int(t, "max_clients", static_cast<std::int64_t>(o.max_clients), 1, 64, source, in));
  return o;
}

}  // namespace

std::vector<AllowedClient> allowed_clients_from_text(const std::string& toml_text, const std::string& source) {
  const toml::table root = parse_toml(toml_text, source);
  for (const auto& [k, v] : root)
    if (k.str() != "clients") throw InputError(source + ": unknown key \"" + std::string(k.str()) + "\" (only [[clients]])");
  return read_allowed_clients(root.get("clients"), source + ": [[clients]]");
}

std::vector<AllowedClient> allowed_clients_from_file(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path.string() + ": cannot open the client allow-list");
  std::ostringstream text;
  text << in.rdbuf();
  return allowed_clients_from_text(text.str(), path.string());
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
  const toml::table root = parse_toml(toml_text, source);
  ServerSettings s;
  s.security = read_security(root.get("security"), source, base_dir);
  s.openigtlink = read_openigtlink(root.get("openigtlink"), source);
  const toml::node* section = root.get("server");
  if (!section) return s;
  if (!section->is_table()) throw InputError(source + ": [server] must be a table");
  const toml::table& t = *section->as_table();
  static const std::set<std::string> known = {
      "endpoint", "events", "store", "queue_depth", "max_frame_bytes", "timing_log",
      "preop", "atlas_cache", "allow_plain_tcp_non_loopback", "idle_release_ms"};
  for (const auto& [k, v] : t)
    if (!known.count(std::string(k.str()))) fail(source, std::string(k.str()), "unknown key");

  s.endpoint = get_string(t, "endpoint", s.endpoint, source);
  s.events = get_string(t, "events", s.events, source);
  s.store = get_string(t, "store", s.store.string(), source);
  if (s.store.empty()) fail(source, "store", "must not be empty");
  s.queue_depth = static_cast<std::size_t>(get_int(t, "queue_depth", 4, 1, 1000, source));
  // 1 KiB .. 2 GiB: a frame must at least hold a NIfTI header; above 2 GiB
  // ZeroMQ and our buffers are not the right tool.
  s.max_frame_bytes = static_cast<std::size_t>(
      get_int(t, "max_frame_bytes", static_cast<std::int64_t>(s.max_frame_bytes), 1024,
              std::int64_t{2} << 30, source));
  s.timing_log = get_string(t, "timing_log", "", source);
  s.atlas_cache = get_string(t, "atlas_cache", "", source);
  s.preop = read_preop(t, source);
  s.allow_plain_tcp_non_loopback =
      get_bool(t, "allow_plain_tcp_non_loopback", s.allow_plain_tcp_non_loopback, source);
  s.idle_release_ms = static_cast<std::int64_t>(
      get_int(t, "idle_release_ms", s.idle_release_ms, 0, std::int64_t{24} * 3600 * 1000, source));
  return s;
}

ServerSettings server_settings_from_file(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path.string() + ": cannot open the configuration file");
  std::ostringstream text;
  text << in.rdbuf();
  return server_settings_from_text(text.str(), path.string(), path.parent_path());
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
