#pragma once
// The OpenIGTLink gateway: a TCP server that 3D Slicer's OpenIGTLinkIF
// connects to as a client. Once each result is stored (just after its
// scan.done: ServerCore::set_result_stored_hook) it sends that result
// (igtl_encoder.h) to each connected client, and a client that connects gets
// the latest result at once. PROTOCOL.md section 16.
//
// Threads: the gateway has one thread of its own, which reads the result
// from the store, packs it and writes it to the sockets (non-blocking, poll).
// publish() and info() never wait for it, so neither the engine nor the
// request socket ever waits for an OpenIGTLink client.
//
// Slow clients: each client has a queue of at most queue_messages messages.
// A new result first drops the client's unsent messages of older results
// (superseded: the client gets the latest), then, should it still not fit,
// the oldest unsent messages go; every drop is counted in
// info().messages_dropped. A message being written is always finished, so
// the stream stays well-formed. A result's messages are shared by all
// clients, not copied: a stalled client holds at most one old message and
// the latest result.
#include <atomic>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "core/label_table.h"
#include "protocol/message.h"
#include "protocol/requests.h"
#include "server/case_store.h"
#include "server/igtl_encoder.h"
#include "server/server_settings.h"

namespace brainshift::server {

// A done scan's result read back from the store; unreadable parts are left
// out and named in problems.
// labels names the models' devices (their short names).
igtl::ResultContent load_igtl_result(const CaseStore& store, const std::string& scan_id, const LabelTable& labels);

class IgtlGateway {
 public:
  // Listens on settings.bind:settings.port (port 0: any free port) and starts
  // the thread, which first loads the newest done scan in the store. Throws
  // std::runtime_error naming the address when it cannot listen.
  IgtlGateway(const OpenIgtlinkSettings& settings, const CaseStore& store, LabelTable labels);
  ~IgtlGateway();  // closes every connection
  IgtlGateway(const IgtlGateway&) = delete;
  IgtlGateway& operator=(const IgtlGateway&) = delete;

  int port() const { return port_; }
  // Any thread, returns at once: queues that stored scan's result for every client.
  void publish(const std::string& scan_id);
  // Any thread, returns at once: sends that scan's deferred image parts (the
  // uncertainty map) once they are stored, after its result.
  void publish_deferred(const std::string& scan_id);
  protocol::OpenIgtlinkInfo info() const;

 private:
  using Shared = std::shared_ptr<const igtl::PackedMessage>;
  struct Client {
    int fd = -1;
    std::string peer;
    std::deque<Shared> queue;
    std::size_t written = 0;  // bytes of queue.front() already sent
  };

  void run();
  void load_and_send(const std::string& scan_id);
  void send_deferred(const std::string& scan_id);
  // supersede: a new result, which drops what the client has not begun of older ones;
  // false for a part that follows the result it belongs to.
  void enqueue(Client& c, const std::vector<Shared>& messages, bool supersede = true);
  void accept_clients();
  bool write_some(Client& c);  // false: the client is gone
  bool drain_input(Client& c);  // false: the client is gone
  void close_client(Client& c, const char* why);
  void wake();

  OpenIgtlinkSettings settings_;
  const CaseStore& store_;
  const LabelTable labels_;
  int listen_fd_ = -1;
  int wake_fd_ = -1;  // eventfd: publish() and the destructor wake poll()
  int port_ = 0;

  std::mutex mutex_;  // guards pending_ and stop_
  std::vector<std::string> pending_;
  std::vector<std::string> pending_deferred_;
  bool stop_ = false;

  // The gateway thread's own state.
  std::vector<Client> clients_;
  std::vector<Shared> latest_;
  std::string latest_scan_id_;

  std::atomic<std::uint64_t> connected_{0}, sent_{0}, dropped_{0};
  std::thread thread_;
};

}  // namespace brainshift::server
