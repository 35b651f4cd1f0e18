#pragma once
// The client's side of the protocol: one DEALER connection for requests and a
// SUB connection for events, with timeouts that become clear messages and
// exit codes instead of a hang.
#include <chrono>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>

#include <zmq.hpp>

#include "exit_codes.h"
#include "handshake_monitor.h"
#include "protocol/curve_keys.h"
#include "protocol/message.h"

namespace brainshift::cli {

// Carries the exit code the command should end with.
class CommandError : public std::runtime_error {
 public:
  CommandError(int exit_code, const std::string& message) : std::runtime_error(message), exit_code_(exit_code) {}
  int exit_code() const { return exit_code_; }

 private:
  int exit_code_;
};

// CURVE keys of this client, or nullopt for plain TCP (loopback servers
// without CURVE).
using CurveKeys = std::optional<protocol::curve::ClientKeys>;

class Connection {
 public:
  Connection(std::string endpoint, std::chrono::milliseconds timeout, CurveKeys curve = std::nullopt);
  ~Connection();

  // Sends the request and returns the reply. Throws CommandError: kExitUnreachable
  // on timeout, kExitError for an error reply (its code and message).
  protocol::Message call(const protocol::Message& request);
  // As call() but returns error replies instead of throwing on them.
  protocol::Message call_raw(const protocol::Message& request);
  std::string next_request_id();
  const std::string& endpoint() const { return endpoint_; }

 private:
  void reconnect();

  std::string endpoint_;
  std::chrono::milliseconds timeout_;
  CurveKeys curve_;
  zmq::context_t context_;
  std::unique_ptr<zmq::socket_t> socket_;
  std::unique_ptr<HandshakeMonitor> monitor_;  // after socket_: destroyed first
  unsigned counter_ = 0;
};

class EventStream {
 public:
  // topic_prefix "" = every event.
  EventStream(const std::string& endpoint, const std::string& topic_prefix = "", const CurveKeys& curve = std::nullopt);
  // nullopt when nothing arrived within timeout. Throws
  // CommandError(kExitUnreachable) when the server refused the handshake.
  std::optional<protocol::Message> next(std::chrono::milliseconds timeout);

 private:
  std::string endpoint_;
  zmq::context_t context_;
  zmq::socket_t socket_;
  std::unique_ptr<HandshakeMonitor> monitor_;
};

}  // namespace brainshift::cli
