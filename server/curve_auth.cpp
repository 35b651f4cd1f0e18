#include "server/curve_auth.h"

#include <iterator>

#include <spdlog/spdlog.h>
#include <zmq_addon.hpp>

#include "core/errors.h"
#include "protocol/transport.h"

namespace brainshift::server {
namespace curve = protocol::curve;
using namespace std::chrono_literals;

namespace {

void add_client(ServerCurve& out, const AllowedClient& c, const std::string& source) {
  const std::string key = curve::z85_to_binary(c.public_z85);
  for (const auto& [k, other] : out.clients_by_key)
    if (other.name == c.name)
      throw InputError(source + ": client name \"" + c.name + "\" is listed twice");
  if (!out.clients_by_key.emplace(key, c).second)
    throw InputError(source + ": the key of \"" + c.name + "\" (" + curve::fingerprint(c.public_z85) +
                     "...) is listed twice");
}

// ZMTP metadata (RFC 23): name length (1 byte), name, value length (4 bytes,
// network order), value.
std::string zap_metadata(const std::string& name, const std::string& value) {
  std::string out;
  out += static_cast<char>(name.size());
  out += name;
  const auto n = static_cast<std::uint32_t>(value.size());
  for (int shift : {24, 16, 8, 0}) out += static_cast<char>((n >> shift) & 0xff);
  out += value;
  return out;
}

}  // namespace

ServerCurve load_server_curve(const SecuritySettings& s) {
  if (!curve::available()) throw InputError("[security] curve = true, but this libzmq has no CURVE support");
  ServerCurve out;
  try {
    out.server.secret_z85 = curve::read_secret_key_file(s.server_secret_key_file);
    out.server.public_z85 = curve::public_from_secret(out.server.secret_z85);
    if (!s.server_public_key_file.empty() &&
        curve::read_public_key_file(s.server_public_key_file) != out.server.public_z85)
      throw InputError(s.server_public_key_file.string() + " is not the public key of " +
                       s.server_secret_key_file.string());
  } catch (const curve::KeyFileError& e) {
    throw InputError(std::string("[security] ") + e.what());
  }
  for (const auto& c : s.clients) add_client(out, c, "[[security.clients]]");
  if (!s.clients_file.empty())
    for (const auto& c : allowed_clients_from_file(s.clients_file)) add_client(out, c, s.clients_file.string());
  if (out.clients_by_key.empty()) throw InputError("[security] the client allow-list is empty: no client could connect");
  return out;
}

ZapHandler::ZapHandler(zmq::context_t& context, std::map<std::string, AllowedClient> clients_by_key)
    : socket_(context, zmq::socket_type::rep), clients_by_key_(std::move(clients_by_key)) {
  socket_.set(zmq::sockopt::linger, 0);
  socket_.bind("inproc://zeromq.zap.01");
  thread_ = std::thread([this] { run(); });
}

ZapHandler::~ZapHandler() {
  running_ = false;
  if (thread_.joinable()) thread_.join();
  socket_.close();
}

void ZapHandler::run() {
  while (running_) {
    try {
      zmq_pollitem_t item{socket_.handle(), 0, ZMQ_POLLIN, 0};
      if (zmq::poll(&item, 1, 100ms) <= 0) continue;
      std::vector<zmq::message_t> request;
      if (!zmq::recv_multipart(socket_, std::back_inserter(request))) continue;
      answer(request);
    } catch (const std::exception& e) {
      // A REP socket that lost its state cannot answer again: every later
      // handshake would then hang, so this is logged loudly.
      spdlog::error("ZAP handler: {}", e.what());
    }
  }
}

// ZAP 1.0 (RFC 27) request: version, request id, domain, address, identity,
// mechanism, credentials...; reply: version, request id, status code, status
// text, user id, metadata.
void ZapHandler::answer(std::vector<zmq::message_t>& request) {
  auto text = [&](std::size_t i) { return i < request.size() ? request[i].to_string() : std::string(); };
  std::string status = "400", status_text = "not allowed", user_id, metadata;
  const std::string domain = text(2), address = text(3), mechanism = text(5), key = text(6);
  if (request.size() < 6 || text(0) != "1.0") {
    status = "500";
    status_text = "malformed ZAP request";
    spdlog::error("ZAP handler: malformed request ({} frames)", request.size());
  } else if (mechanism != "CURVE" || key.size() != 32) {
    ++refused_;
    log_refusal("", domain, address, "mechanism " + mechanism + " (only CURVE is accepted)");
  } else if (domain != kRequestsZapDomain && domain != kEventsZapDomain) {
    ++refused_;
    log_refusal(curve::binary_to_z85(key), domain, address, "unknown ZAP domain");
  } else if (auto it = clients_by_key_.find(key); it == clients_by_key_.end()) {
    ++refused_;
    log_refusal(curve::binary_to_z85(key), domain, address, "key not in the allow-list");
  } else {
    ++accepted_;
    status = "200";
    status_text = "OK";
    user_id = std::string(to_string(it->second.role));
    metadata = zap_metadata(protocol::transport::kClientNameProperty, it->second.name);
    spdlog::info("CURVE client \"{}\" ({}, key {}...) connected to {} from {}", it->second.name, user_id,
                 curve::fingerprint(it->second.public_z85), domain, address);
  }
  const std::vector<std::string> reply = {"1.0", text(1), status, status_text, user_id, metadata};
  for (std::size_t i = 0; i < reply.size(); ++i)
    socket_.send(zmq::buffer(reply[i]), i + 1 < reply.size() ? zmq::send_flags::sndmore : zmq::send_flags::none);
}

void ZapHandler::log_refusal(const std::string& key_z85, const std::string& domain, const std::string& address,
                             const std::string& why) {
  const auto now = std::chrono::steady_clock::now();
  const std::string who = domain + " " + (key_z85.empty() ? "mechanism:" + address : key_z85);
  auto it = last_logged_.find(who);
  if (it != last_logged_.end() && now - it->second < 60s) return;
  if (last_logged_.size() > 1024) last_logged_.clear();  // bounded, whatever a stranger tries
  last_logged_[who] = now;
  spdlog::warn("refused a connection to {} from {}: {}{} (refusals so far: {}; each key logged once a minute)",
               domain.empty() ? "?" : domain, address, why,
               key_z85.empty() ? "" : ", key " + curve::fingerprint(key_z85) + "...", refused_.load());
}

}  // namespace brainshift::server

namespace brainshift::server {

class HandshakeFailureLog::Monitor : public zmq::monitor_t {
 public:
  explicit Monitor(std::string what) : what_(std::move(what)) {}
  std::uint64_t failures = 0;

  void on_event_handshake_failed_protocol(const zmq_event_t&, const char* endpoint) override { failed(endpoint); }
  void on_event_handshake_failed_no_detail(const zmq_event_t&, const char* endpoint) override { failed(endpoint); }

 private:
  void failed(const char* endpoint) {
    ++failures;
    const auto now = std::chrono::steady_clock::now();
    if (logged_once_ && now - last_logged_ < std::chrono::minutes(1)) return;
    logged_once_ = true;
    last_logged_ = now;
    spdlog::warn("a client failed the CURVE handshake on the {} socket {} (no CURVE, or another server key); "
                 "{} such failure(s) so far, logged once a minute",
                 what_, endpoint, failures);
  }
  std::string what_;
  bool logged_once_ = false;
  std::chrono::steady_clock::time_point last_logged_;
};

HandshakeFailureLog::HandshakeFailureLog(zmq::socket_t& socket, std::string what)
    : monitor_(std::make_unique<Monitor>(what)) {
  monitor_->init(socket, "inproc://brainshift-handshake-" + what,
                 ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL | ZMQ_EVENT_HANDSHAKE_FAILED_NO_DETAIL);
}

HandshakeFailureLog::~HandshakeFailureLog() = default;

void HandshakeFailureLog::poll() {
  while (monitor_->check_event(0)) {
  }
}

std::uint64_t HandshakeFailureLog::failures() const { return monitor_->failures; }

}  // namespace brainshift::server
