#pragma once
// Shared by the fault and soak tests: brainshiftd as a real child process
// (optionally under mpirun), a protocol client on a DEALER socket, an event
// recorder on a SUB socket, and /proc readings of the daemon (RSS, fds).
#include <sys/types.h>

#include <chrono>
#include <condition_variable>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <zmq.hpp>

#include "process.h"
#include "protocol/events.h"
#include "protocol/requests.h"

namespace brainshift::e2e {

struct DaemonSpec {
  std::filesystem::path work_dir;  // logs and the ready file go here
  std::filesystem::path config;
  std::filesystem::path store;
  std::string name;       // prefix of the log files
  int mpi_ranks = 0;      // 0: no mpirun
  std::vector<std::string> env;  // NAME=VALUE pairs for the daemon (every rank: mpirun -x)
  std::vector<std::string> extra_args;  // appended to brainshiftd's command line
};

class Daemon {
 public:
  // Starts and waits for the ready file (throws with the log when it fails).
  explicit Daemon(DaemonSpec spec);
  Process& process() { return *process_; }
  pid_t rank0_pid() const { return rank0_pid_; }
  std::string log() const;

  std::string endpoint, events;
  std::optional<int> igtl_port;  // when the OpenIGTLink gateway is on

 private:
  DaemonSpec spec_;
  std::unique_ptr<Process> process_;
  pid_t rank0_pid_ = -1;
};

// A daemon working in dir: configuration dir/test.toml, store dir/store.
DaemonSpec spec_in(const std::filesystem::path& dir, const std::string& name);
// The brainshift CLI against the daemon (its endpoints, 20 s per request),
// run in work_dir.
RunResult run_cli(const Daemon& d, const std::filesystem::path& work_dir, const std::vector<std::string>& args,
                  double timeout_s = 600);

// One DEALER connection; calls wait for their own reply (by request_id).
class Client {
 public:
  explicit Client(const std::string& endpoint);
  // nullopt when no reply came within timeout.
  std::optional<protocol::Message> call(const protocol::Message& request,
                                        std::chrono::milliseconds timeout = std::chrono::seconds(30));
  std::string next_id();

  protocol::StatusReply status();
  void load_preop(const std::string& t1_bytes, const std::string& labels_bytes,
                  std::optional<std::string> patient_id = std::nullopt);
  // The raw reply (a scan.push reply or an error). An empty labels or image
  // is not sent (an image alone is a scan).
  protocol::Message push(const std::string& labels_bytes, const std::string& image_bytes,
                         const std::optional<std::string>& client_scan_id);
  protocol::Message result(const std::string& scan_id, const std::vector<protocol::ResultPart>& parts);
  protocol::ScanListReply list(std::uint64_t limit = protocol::kMaxScanListLimit);
  // Polls status until ready (throws after timeout).
  void wait_ready(std::chrono::seconds timeout);

 private:
  zmq::context_t context_{1};
  zmq::socket_t socket_;
  int counter_ = 0;
};

// Records every event the daemon publishes, from a thread of its own.
class EventRecorder {
 public:
  explicit EventRecorder(const std::string& events_endpoint);
  ~EventRecorder();
  // Waits until pred holds for some recorded event (checked from the oldest);
  // returns it, or nullopt on timeout.
  std::optional<protocol::Message> wait_for(const std::function<bool(const protocol::Message&)>& pred,
                                            std::chrono::milliseconds timeout);
  std::vector<protocol::Message> snapshot();
  // Events with the time they were received.
  using Timed = std::pair<std::chrono::steady_clock::time_point, protocol::Message>;
  std::vector<Timed> timed_snapshot();

 private:
  void run(std::string endpoint);
  std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<protocol::Message> events_;
  std::vector<std::chrono::steady_clock::time_point> times_;
  bool stop_ = false;
  std::thread thread_;
};

// Every result part, models included.
std::vector<protocol::ResultPart> all_result_parts();
// frame name -> bytes of a scan.result reply.
std::map<std::string, std::string> frames_by_name(const protocol::Message& result_reply);
// Pulls parts of a done scan, asking again while some are still being made
// (metrics.json, field.h5 and report.png follow event.scan.done).
std::map<std::string, std::string> pull_complete(Client& c, const std::string& scan_id,
                                                 const std::vector<protocol::ResultPart>& parts,
                                                 std::chrono::seconds timeout = std::chrono::seconds(120));

std::uint64_t resident_kib(pid_t pid);  // VmRSS from /proc/<pid>/status
std::size_t open_fds(pid_t pid);        // entries of /proc/<pid>/fd
std::vector<pid_t> child_pids(pid_t parent);

// Writes the synthetic preop and `count` distinct synthetic scans into dir;
// returns (labels bytes, image bytes) per scan.
struct ScanBytes {
  std::string labels, image;
};
std::vector<ScanBytes> write_synthetic_inputs(const std::filesystem::path& dir, int count, double voxel_scale = 1.0);

// A coarse mesh, so the synthetic head warms up in seconds.
std::string test_config_text(int queue_depth);

}  // namespace brainshift::e2e
