#pragma once
// The daemon's logic without sockets: request handling (socket thread), the
// job loop (engine thread), shared state for status, events and the timing
// log. daemon.cpp wires it to ZeroMQ and MPI; tests drive it directly.
// One class, in four files along its threads: request_handlers.cpp (socket
// thread), job_runner.cpp (engine thread: warm-up, scans, deferred outputs),
// crash_recovery.cpp (start-up: warm state, re-queued scans, repairs) and
// server_core.cpp (construction, status, events, the job loop's step).
//
// Threads: handle_*() run on the socket thread and never wait for the engine
// (they read a snapshot under a short mutex). start()/step() run on the engine
// thread, the only one that runs the engine through the EnginePort
// (MPI_THREAD_FUNNELED); the socket thread reads only what the port fixed at
// construction (label_table(), max_image_bytes(); engine_port.h).
#include <atomic>
#include <chrono>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "protocol/message.h"
#include "protocol/requests.h"
#include "core/fault_injection.h"
#include "protocol/timing_log.h"
#include "server/case_store.h"
#include "server/engine_port.h"
#include "server/roles.h"
#include "server/scan_queue.h"
#include "server/server_settings.h"

namespace brainshift::server {

class ServerCore {
 public:
  // Called from either thread with a complete event message; must be thread-safe.
  using EventSink = std::function<void(protocol::Message)>;

  ServerCore(ServerSettings settings, CaseStore& store, EnginePort& engine, EventSink events,
             std::map<std::string, std::string> versions = {});
  ~ServerCore();

  // ---- socket thread -------------------------------------------------------
  // Decodes and answers one request from `peer`; never throws: every failure
  // is a typed error reply. The peer's role is checked right after the common
  // header is decoded, before any request field or frame is interpreted.
  protocol::Message handle_wire(std::vector<std::string> wire, const Peer& peer);
  protocol::Message handle(const protocol::Message& request, const Peer& peer);
  // As above for an unauthenticated local client (a server without CURVE).
  protocol::Message handle_wire(std::vector<std::string> wire) {
    return handle_wire(std::move(wire), Peer::unauthenticated_local());
  }
  protocol::StatusReply status() const;
  // Adds what other parts of the daemon report (the OpenIGTLink gateway's
  // counters) to every status reply (not to status()). Set before the socket thread starts;
  // called on the socket thread, so it must not wait.
  void set_status_extension(std::function<void(protocol::StatusReply&)> extend) {
    status_extension_ = std::move(extend);
  }
  // Called on the engine thread once a result is durable in the store (it is
  // served from memory before that, after event.scan.done): readers of the
  // store, such as the OpenIGTLink gateway, take it from there. Must not wait.
  void set_result_stored_hook(std::function<void(const std::string& scan_id)> hook) {
    result_stored_ = std::move(hook);
  }
  // The same once a result's deferred parts (uncertainty.nii, report.png, ...)
  // are stored.
  void set_deferred_stored_hook(std::function<void(const std::string& scan_id)> hook) {
    deferred_stored_ = std::move(hook);
  }
  bool shutdown_requested() const { return shutdown_.load(); }
  const protocol::Limits& inbound_limits() const { return limits_; }

  // ---- engine thread -------------------------------------------------------
  // Restores the warm state from the store (or queues the configured default
  // preop) and re-queues acknowledged scans that have no result.
  void start();
  // Runs one job (a preop warm-up first, else one scan) if one arrives within
  // `wait`; returns whether a job ran.
  bool step(std::chrono::milliseconds wait);
  // Stops taking jobs (signal or shutdown request); wakes step().
  void request_stop();

 private:
  struct PreopJob;
  struct DecodedScan;
  struct UnwrittenResult;

  protocol::Message on_status(const protocol::Message& m);
  protocol::Message on_preop_load(const protocol::Message& m);
  protocol::Message on_scan_push(const protocol::Message& m);
  protocol::Message on_scan_result(const protocol::Message& m);
  protocol::Message on_scan_list(const protocol::Message& m);
  protocol::Message on_shutdown(const protocol::Message& m);

  void run_preop_job(PreopJob job);
  void run_scan(const std::string& scan_id);
  // The one place where a scan's result becomes available: from here on it
  // is pulled (from memory until write_result has stored it) and scan.done
  // is out. A gateway that forwards results (e.g. to a navigation system)
  // hooks in here.
  std::shared_ptr<const UnwrittenResult> publish_result(const ScanRecord& record, EngineScanOutput out,
                                                        double seconds);
  // Makes a published result durable and returns true; a refused write
  // withdraws it, reports the scan failed until it is computed again and
  // returns false.
  bool write_result(const UnwrittenResult& result, const std::string& preop_id);
  void add_deferred_outputs(const std::string& scan_id, const std::string& preop_id);
  void fail_scan(const ScanRecord& record, protocol::ErrorCode code, const std::string& message,
                 const std::string& stage);
  void result_not_stored(const ScanRecord& record, const std::string& why);
  void find_incomplete_results();
  // Makes a lost deferred part again from the stored part it re-encodes
  // (result_outputs.h remade_from); logs when it cannot.
  void remake_part(const std::string& scan_id, protocol::ResultPart part, const std::string& source_file);
  void repair_scan(const std::string& scan_id);
  void emit(protocol::Message event);
  void log_stage(protocol::StageTiming timing);
  DecodedScan decode_scan(const PushedScan& input) const;

  ServerSettings settings_;
  CaseStore& store_;
  EnginePort& engine_;
  EventSink events_;
  std::function<void(protocol::StatusReply&)> status_extension_;
  std::function<void(const std::string&)> result_stored_;
  std::function<void(const std::string&)> deferred_stored_;
  std::map<std::string, std::string> versions_;
  protocol::Limits limits_;
  ScanQueue queue_;
  std::unique_ptr<protocol::TimingLogFile> timing_log_;
  std::atomic<bool> shutdown_{false};
  std::atomic<bool> stopping_{false};

  // Shared state, under mutex_.
  mutable std::mutex mutex_;
  protocol::ServerState state_ = protocol::ServerState::kIdle;
  std::optional<protocol::Progress> progress_;
  std::string loading_preop_id_;  // non-empty while a warm-up is pending or running
  std::string ready_preop_id_;    // non-empty once the engine is warm
  // The patient of each (preop.load patient_id, kept in the store): a scan
  // of another patient is refused before it is stored.
  std::optional<std::string> loading_patient_id_, ready_patient_id_;
  // The label map (preop.load label_table) of the ready preop, null when it
  // had none: the intraop labels of its scans use the same values.
  std::shared_ptr<const protocol::LabelMap> ready_label_map_;
  std::optional<protocol::MeshSize> mesh_size_;
  std::optional<std::string> current_scan_;
  std::optional<std::string> current_stage_;
  std::optional<protocol::ErrorInfo> last_error_;
  std::unique_ptr<PreopJob> pending_preop_;
  std::map<std::string, std::shared_ptr<DecodedScan>> decoded_;  // pushed, not yet run
  std::set<std::string> deferred_pending_;  // done; field.h5/report.png still being made
  // Published, not yet in the store: served from memory. A crash before the
  // write leaves the scan acknowledged without a result, so a restart
  // computes it again from its stored input.
  std::map<std::string, std::shared_ptr<const UnwrittenResult>> unwritten_results_;
  std::vector<std::string> unstored_results_;  // computed, refused by the store; retried
  std::vector<std::string> repairs_;  // engine thread: done scans missing deferred outputs
  int ranks_ = 1;
  FaultPoint result_write_fault_{"result_write"};  // BRAINSHIFT_INJECT_FAULT, see core/fault_injection.h
};

}  // namespace brainshift::server
