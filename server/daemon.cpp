#include "server/daemon.h"

#include <malloc.h>
#include <unistd.h>

#include <deque>
#include <fstream>
#include <mutex>
#include <thread>

#include <spdlog/spdlog.h>
#include <zmq.hpp>

#include "protocol/events.h"
#include "protocol/transport.h"
#include "server/case_store.h"
#include "server/curve_auth.h"
#include "server/igtl_gateway.h"
#include "server/server_core.h"

namespace brainshift::server {
namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {

// Events come from both threads; only the socket thread touches the PUB socket.
class EventOutbox {
 public:
  void push(protocol::Message m) {
    std::lock_guard lock(mutex_);
    events_.push_back(std::move(m));
  }
  std::deque<protocol::Message> drain() {
    std::lock_guard lock(mutex_);
    return std::exchange(events_, {});
  }

 private:
  std::mutex mutex_;
  std::deque<protocol::Message> events_;
};

void write_ready_file(const fs::path& path, const std::string& endpoint, const std::string& events,
                      const IgtlGateway* igtl) {
  const fs::path tmp = path.string() + ".tmp";
  {
    std::ofstream out(tmp);
    nlohmann::json ready{{"endpoint", endpoint}, {"events", events}, {"pid", ::getpid()}};
    if (igtl) ready["igtl_port"] = igtl->port();
    out << ready.dump() << '\n';
  }
  fs::rename(tmp, path);
}

void publish_all(zmq::socket_t& pub, EventOutbox& outbox) {
  for (const auto& event : outbox.drain()) {
    try {
      protocol::transport::publish(pub, event);
    } catch (const std::exception& e) {
      spdlog::warn("event not published: {}", e.what());
    }
  }
}

// Answers requests and publishes events until `running` is cleared. Never
// waits for the engine: ServerCore's handlers only take short locks.
// With CURVE the role is the ZAP User-Id libzmq attached to the message;
// without it the peer is an unauthenticated loopback client.
void socket_loop(zmq::socket_t& router, zmq::socket_t& pub, ServerCore& core, EventOutbox& outbox,
                 const std::atomic<bool>& running, bool curve) {
  // Monitors are read by this thread, the one that owns the sockets.
  std::vector<std::unique_ptr<HandshakeFailureLog>> handshake_logs;
  if (curve) {
    handshake_logs.push_back(std::make_unique<HandshakeFailureLog>(router, "requests"));
    handshake_logs.push_back(std::make_unique<HandshakeFailureLog>(pub, "events"));
  }
  while (running) {
    for (auto& log : handshake_logs) log->poll();
    try {
      auto request = protocol::transport::receive_request(router, 10ms);
      if (request) {
        if (request->wire.empty()) {
          spdlog::warn("dropped a message without an envelope delimiter (cannot be answered)");
        } else {
          const Peer peer = curve ? Peer::from_zap(request->user_id, request->client_name)
                                  : Peer::unauthenticated_local();
          const protocol::Message reply = core.handle_wire(std::move(request->wire), peer);
          protocol::transport::send_reply(router, request->envelope, reply);
        }
      }
    } catch (const std::exception& e) {
      // A peer that vanished mid-reply must not stop the others being served.
      spdlog::warn("socket loop: {}", e.what());
    }
    publish_all(pub, outbox);
  }
}

// Runs jobs until stopped; after idle_release of no job (if > 0), returns
// the free heap pages to the system once (see ServerSettings::idle_release_ms).
void run_jobs(ServerCore& core, const std::atomic<bool>& stop, std::chrono::milliseconds idle_release) {
  auto last_job = std::chrono::steady_clock::now();
  bool released = true;
  while (!stop && !core.shutdown_requested()) {
    if (core.step(50ms)) {
      last_job = std::chrono::steady_clock::now();
      released = false;
    } else if (!released && idle_release.count() > 0 &&
               std::chrono::steady_clock::now() - last_job >= idle_release) {
      malloc_trim(0);
      released = true;
    }
  }
}

}  // namespace

int run_daemon(const DaemonOptions& options, EnginePort& engine, const std::atomic<bool>& stop) {
  const ServerSettings& s = options.settings;
  std::unique_ptr<CaseStore> store;
  std::unique_ptr<IgtlGateway> igtl;  // after the store, which it reads
  zmq::context_t context(1);
  // Declared before the sockets so that it outlives them: a CURVE socket
  // without a ZAP handler would admit every key.
  std::unique_ptr<ZapHandler> zap;
  zmq::socket_t router(context, zmq::socket_type::router);
  zmq::socket_t pub(context, zmq::socket_type::pub);
  protocol::Limits limits = protocol::Limits::server_inbound();
  limits.max_frame_bytes = s.max_frame_bytes;
  try {
    store = std::make_unique<CaseStore>(s.store);
    if (s.security.curve) {
      const ServerCurve keys = load_server_curve(s.security);
      zap = std::make_unique<ZapHandler>(context, keys.clients_by_key);
      protocol::curve::set_server_options(router, keys.server.secret_z85, kRequestsZapDomain);
      protocol::curve::set_server_options(pub, keys.server.secret_z85, kEventsZapDomain);
      spdlog::info("CURVE on: server key {}..., {} allowed client key(s)",
                   protocol::curve::fingerprint(keys.server.public_z85), keys.clients_by_key.size());
    } else {
      spdlog::info("CURVE off: every client is an unauthenticated local one (shutdown {})",
                   s.security.allow_unauthenticated_shutdown ? "allowed" : "refused");
      for (const auto& ep : {s.endpoint, s.events})
        if (!is_local_endpoint(ep))
          spdlog::warn("plain TCP on the non-loopback endpoint {} (allow_plain_tcp_non_loopback): anyone on that "
                       "network can send any request and read every event", ep);
    }
    // Refuse oversized frames at the socket before they are allocated.
    protocol::transport::apply_hard_frame_cap(router, limits);
    router.set(zmq::sockopt::linger, 0);
    // Replies to a client that does not read them are dropped, not queued
    // forever. A well-behaved client has one request outstanding; the limit
    // is in messages, not bytes, and a result reply is tens of MB, so it is
    // kept small: 100 measured 640 MB held for one client that never read.
    router.set(zmq::sockopt::router_mandatory, 0);
    router.set(zmq::sockopt::sndhwm, 4);
    pub.set(zmq::sockopt::linger, 200);
    router.bind(s.endpoint);
    pub.bind(s.events);
    if (s.openigtlink.enabled) igtl = std::make_unique<IgtlGateway>(s.openigtlink, *store, engine.label_table());
  } catch (const std::exception& e) {
    spdlog::critical("cannot start: {}", e.what());
    engine.stop_workers();
    return 1;
  }
  const std::string endpoint = router.get(zmq::sockopt::last_endpoint);
  const std::string events = pub.get(zmq::sockopt::last_endpoint);

  EventOutbox outbox;
  int exit_code = 0;
  {
    IgtlGateway* gateway = igtl.get();
    ServerCore core(s, *store, engine, [&outbox](protocol::Message m) { outbox.push(std::move(m)); },
                    {{"brainshiftd", "0.1.0"}});
    if (gateway) {
      core.set_status_extension([gateway](protocol::StatusReply& r) { r.openigtlink = gateway->info(); });
      // The gateway reads results from the store: it is told once one is
      // there, which is just after event.scan.done (served from memory first).
      core.set_result_stored_hook([gateway](const std::string& scan_id) { gateway->publish(scan_id); });
      core.set_deferred_stored_hook([gateway](const std::string& scan_id) { gateway->publish_deferred(scan_id); });
    }
    std::atomic<bool> sockets_running{true};
    std::thread socket_thread(socket_loop, std::ref(router), std::ref(pub), std::ref(core), std::ref(outbox),
                              std::cref(sockets_running), s.security.curve);
    try {
      core.start();
      if (!options.ready_file.empty()) write_ready_file(options.ready_file, endpoint, events, igtl.get());
      spdlog::info("brainshiftd listening on {} (events {}), store {}, {} MPI rank(s)", endpoint, events,
                   s.store.string(), engine.ranks());
      run_jobs(core, stop, std::chrono::milliseconds(s.idle_release_ms));
    } catch (const std::exception& e) {
      spdlog::critical("engine loop: {}", e.what());
      exit_code = 1;
    }
    core.request_stop();
    outbox.push(protocol::make_event(protocol::ServerShutdownEvent{
        stop ? "signal" : (core.shutdown_requested() ? "shutdown request" : "error")}));
    // Give the socket thread a moment to answer the shutdown request and
    // publish the last events before it stops.
    std::this_thread::sleep_for(100ms);
    sockets_running = false;
    socket_thread.join();
    publish_all(pub, outbox);
  }
  engine.stop_workers();
  spdlog::info("brainshiftd stopped");
  return exit_code;
}

}  // namespace brainshift::server
