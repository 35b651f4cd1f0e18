#pragma once
// Turns a refused ZeroMQ handshake into a clear error instead of silence. A
// CURVE server refuses a key outside its allow-list (ZAP status 400), a client
// without CURVE, or one holding the wrong server key; libzmq hides all of
// these from the sending and receiving calls and just retries. A socket
// monitor sees them.
#include <memory>
#include <optional>
#include <string>

#include <zmq.hpp>

namespace brainshift::cli {

class HandshakeMonitor {
 public:
  // Attach before socket.connect(). curve: whether this client uses CURVE (for the advice).
  HandshakeMonitor(zmq::socket_t& socket, std::string endpoint, bool curve);
  ~HandshakeMonitor();
  HandshakeMonitor(const HandshakeMonitor&) = delete;
  HandshakeMonitor& operator=(const HandshakeMonitor&) = delete;

  // Reads the pending monitor events; the reason once a handshake failed
  // before any succeeded, else nullopt.
  std::optional<std::string> refusal();

 private:
  class Events;
  std::unique_ptr<Events> events_;
};

}  // namespace brainshift::cli
