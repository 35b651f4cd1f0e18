#pragma once
// CURVE authentication of brainshiftd (PROTOCOL.md section 13): the server's
// keys and allow-list read from the configuration, and the ZAP handler that
// admits only listed client keys and hands libzmq each one's role.
#include <atomic>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include <zmq.hpp>

#include "protocol/curve_keys.h"
#include "server/server_settings.h"

namespace brainshift::server {

// ZAP domains of the two sockets, so a log line says which one a peer tried.
inline constexpr const char* kRequestsZapDomain = "brainshift.requests";
inline constexpr const char* kEventsZapDomain = "brainshift.events";

struct ServerCurve {
  protocol::curve::KeyPair server;
  std::map<std::string, AllowedClient> clients_by_key;  // by the 32-byte binary public key
};

// Reads the server's secret key (refused when group/other may read it), the
// optional public key file (must match the secret key), and the allow-list
// (inline entries plus clients_file). Throws InputError naming the file.
ServerCurve load_server_curve(const SecuritySettings& settings);

// A REP socket on inproc://zeromq.zap.01 in its own thread. It must exist
// before a CURVE socket of the same context binds and outlive those sockets:
// libzmq 4.3 admits every CURVE client when no ZAP handler is bound.
class ZapHandler {
 public:
  // Binds at once (throws zmq::error_t when another handler holds the address).
  ZapHandler(zmq::context_t& context, std::map<std::string, AllowedClient> clients_by_key);
  ~ZapHandler();  // stops and joins the thread, closes the socket
  ZapHandler(const ZapHandler&) = delete;
  ZapHandler& operator=(const ZapHandler&) = delete;

  std::uint64_t accepted() const { return accepted_; }
  std::uint64_t refused() const { return refused_; }

 private:
  void run();
  void answer(std::vector<zmq::message_t>& request);
  void log_refusal(const std::string& key_z85, const std::string& domain, const std::string& address,
                   const std::string& why);

  zmq::socket_t socket_;
  std::map<std::string, AllowedClient> clients_by_key_;
  std::atomic<bool> running_{true};
  std::atomic<std::uint64_t> accepted_{0}, refused_{0};
  // A refused client reconnects every few hundred ms: one log line per key a minute.
  std::map<std::string, std::chrono::steady_clock::time_point> last_logged_;
  std::thread thread_;
};

// Handshakes that fail before the ZAP handler is asked (a client without
// CURVE, or one holding another server key) are invisible to it; a socket
// monitor sees them. Logged as a count at most once a minute per socket (the
// peer address is not in libzmq's event, only the local endpoint).
class HandshakeFailureLog {
 public:
  HandshakeFailureLog(zmq::socket_t& socket, std::string what);  // what: "requests", "events"
  ~HandshakeFailureLog();
  // Reads pending monitor events without blocking; call from the socket's thread.
  void poll();
  std::uint64_t failures() const;

 private:
  class Monitor;
  std::unique_ptr<Monitor> monitor_;
};

}  // namespace brainshift::server
