#include "handshake_monitor.h"

#include <atomic>

namespace brainshift::cli {

class HandshakeMonitor::Events : public zmq::monitor_t {
 public:
  Events(std::string endpoint, bool curve) : endpoint_(std::move(endpoint)), curve_(curve) {}
  std::optional<std::string> failure;
  bool succeeded = false;

  void on_event_handshake_succeeded(const zmq_event_t&, const char*) override { succeeded = true; }
  void on_event_handshake_failed_auth(const zmq_event_t& e, const char*) override {
    fail("brainshiftd at " + endpoint_ + " refused this client's key at the CURVE handshake (ZAP status " +
         std::to_string(e.value) + "): the key is not in the server's allow-list");
  }
  void on_event_handshake_failed_protocol(const zmq_event_t&, const char*) override { closed(); }
  void on_event_handshake_failed_no_detail(const zmq_event_t&, const char*) override { closed(); }
  // The server drops a handshake it cannot accept (mechanism mismatch, wrong server key).
  void on_event_disconnected(const zmq_event_t&, const char*) override {
    if (!succeeded) closed();
  }

 private:
  void fail(std::string why) {
    if (!succeeded && !failure) failure = std::move(why);
  }
  void closed() {
    fail(curve_ ? "the connection to " + endpoint_ +
                      " was closed during the CURVE handshake: is --server-key the server's public key, and "
                      "does the server use CURVE?"
                : "the connection to " + endpoint_ +
                      " was closed during the handshake: the server probably requires CURVE; give --key and "
                      "--server-key");
  }
  std::string endpoint_;
  bool curve_;
};

HandshakeMonitor::HandshakeMonitor(zmq::socket_t& socket, std::string endpoint, bool curve)
    : events_(std::make_unique<Events>(std::move(endpoint), curve)) {
  // One inproc address per monitored socket in this process.
  static std::atomic<unsigned> counter{0};
  const std::string address = "inproc://handshake-monitor-" + std::to_string(counter++);
  events_->init(socket, address,
                ZMQ_EVENT_HANDSHAKE_SUCCEEDED | ZMQ_EVENT_HANDSHAKE_FAILED_AUTH | ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL |
                    ZMQ_EVENT_HANDSHAKE_FAILED_NO_DETAIL | ZMQ_EVENT_DISCONNECTED);
}

HandshakeMonitor::~HandshakeMonitor() = default;

std::optional<std::string> HandshakeMonitor::refusal() {
  while (events_->check_event(0)) {
  }
  return events_->failure;
}

}  // namespace brainshift::cli
