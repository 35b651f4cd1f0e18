#include "daemon_harness.h"

#include <dirent.h>
#include <stdlib.h>

#include <cstdlib>

#include <algorithm>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include <nlohmann/json.hpp>

#include "protocol/media.h"
#include "protocol/transport.h"
#include "synthetic_case.h"

namespace brainshift::e2e {
namespace fs = std::filesystem;
using namespace protocol;
using namespace std::chrono_literals;

Daemon::Daemon(DaemonSpec spec) : spec_(std::move(spec)) {
  const fs::path ready = spec_.work_dir / (spec_.name + ".ready");
  fs::remove(ready);
  std::vector<std::string> argv;
  std::vector<std::string> exported;
  if (spec_.mpi_ranks > 0)
    argv = {MPIEXEC_BIN, "--allow-run-as-root", "--oversubscribe", "-np", std::to_string(spec_.mpi_ranks)};
  for (const auto& kv : spec_.env) {
    const std::string name = kv.substr(0, kv.find('='));
    ::setenv(name.c_str(), kv.substr(kv.find('=') + 1).c_str(), 1);
    exported.push_back(name);
    if (spec_.mpi_ranks > 0) argv.insert(argv.end(), {"-x", name});
  }
  // By hand: BRAINSHIFT_DAEMON_WRAPPER="/usr/bin/heaptrack -o /tmp/bs" runs
  // the daemon under a memory profiler (space-separated, absolute path first).
  if (const char* wrapper = std::getenv("BRAINSHIFT_DAEMON_WRAPPER")) {
    std::istringstream words(wrapper);
    for (std::string w; words >> w;) argv.push_back(w);
  }
  for (const std::string& a : {std::string(BRAINSHIFTD_BIN), std::string("--config"), spec_.config.string(),
                               std::string("--store"), spec_.store.string(), std::string("--endpoint"),
                               std::string("tcp://127.0.0.1:*"), std::string("--events"),
                               std::string("tcp://127.0.0.1:*"), std::string("--ready-file"), ready.string()})
    argv.push_back(a);
  argv.insert(argv.end(), spec_.extra_args.begin(), spec_.extra_args.end());
  process_ = std::make_unique<Process>(argv, spec_.work_dir / (spec_.name + ".out"),
                                       spec_.work_dir / (spec_.name + ".err"));
  for (const auto& name : exported) ::unsetenv(name.c_str());
  const auto until = std::chrono::steady_clock::now() + 120s;
  while (!fs::exists(ready) && std::chrono::steady_clock::now() < until && process_->running())
    std::this_thread::sleep_for(50ms);
  if (!fs::exists(ready)) throw std::runtime_error(spec_.name + " did not start: " + log());
  const auto r = nlohmann::json::parse(read_file(ready));
  endpoint = r.at("endpoint").get<std::string>();
  events = r.at("events").get<std::string>();
  rank0_pid_ = r.at("pid").get<pid_t>();
  if (r.contains("igtl_port")) igtl_port = r.at("igtl_port").get<int>();
}

// spdlog writes to stdout; MPI and crashes to stderr.
std::string Daemon::log() const {
  return read_file(spec_.work_dir / (spec_.name + ".out")) + read_file(spec_.work_dir / (spec_.name + ".err"));
}

// ---------------------------------------------------------------- client

Client::Client(const std::string& endpoint) : socket_(context_, zmq::socket_type::dealer) {
  socket_.set(zmq::sockopt::linger, 0);
  socket_.connect(endpoint);
}

std::string Client::next_id() { return "t-" + std::to_string(++counter_); }

std::optional<Message> Client::call(const Message& request, std::chrono::milliseconds timeout) {
  transport::send_request(socket_, request);
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) return std::nullopt;
    auto reply = transport::receive_reply(socket_, Limits::client_inbound(), left);
    if (!reply) return std::nullopt;
    if (reply->request_id() == request.request_id()) return reply;
  }
}

StatusReply Client::status() {
  auto r = call(make_status_request(next_id()));
  if (!r) throw std::runtime_error("status: no reply");
  throw_if_error(*r);
  return parse_status_reply(*r);
}

void Client::load_preop(const std::string& t1_bytes, const std::string& labels_bytes,
                        std::optional<std::string> patient_id) {
  PreopLoadRequest req;
  req.patient_id = std::move(patient_id);
  req.t1 = media::nifti_frame("t1", t1_bytes);
  req.labels = media::nifti_frame("labels", labels_bytes);
  auto r = call(make_preop_load_request(next_id(), req));
  if (!r) throw std::runtime_error("preop.load: no reply");
  throw_if_error(*r);
}

DaemonSpec spec_in(const fs::path& dir, const std::string& name) {
  DaemonSpec s;
  s.work_dir = dir;
  s.config = dir / "test.toml";
  s.store = dir / "store";
  s.name = name;
  return s;
}

RunResult run_cli(const Daemon& d, const fs::path& work_dir, const std::vector<std::string>& args, double timeout_s) {
  std::vector<std::string> argv = {BRAINSHIFT_BIN, "--server", d.endpoint, "--events", d.events, "--timeout", "20"};
  argv.insert(argv.end(), args.begin(), args.end());
  return run(argv, work_dir, timeout_s);
}

Message Client::push(const std::string& labels_bytes, const std::string& image_bytes,
                     const std::optional<std::string>& client_scan_id) {
  ScanPushRequest req;
  if (!labels_bytes.empty()) req.labels = media::nifti_frame("labels", labels_bytes);
  if (!image_bytes.empty()) req.image = media::nifti_frame("image", image_bytes);
  req.client_scan_id = client_scan_id;
  auto r = call(make_scan_push_request(next_id(), req), 60s);
  if (!r) throw std::runtime_error("scan.push: no reply");
  return *r;
}

Message Client::result(const std::string& scan_id, const std::vector<ResultPart>& parts) {
  ScanResultRequest req;
  req.scan_id = scan_id;
  req.parts = parts;
  auto r = call(make_scan_result_request(next_id(), req), 60s);
  if (!r) throw std::runtime_error("scan.result: no reply");
  return *r;
}

ScanListReply Client::list(std::uint64_t limit) {
  auto r = call(make_scan_list_request(next_id(), {limit}));
  if (!r) throw std::runtime_error("scan.list: no reply");
  throw_if_error(*r);
  return parse_scan_list_reply(*r);
}

void Client::wait_ready(std::chrono::seconds timeout) {
  const auto until = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < until) {
    if (status().state == ServerState::kReady) return;
    std::this_thread::sleep_for(100ms);
  }
  throw std::runtime_error("the daemon did not become ready in time");
}

// ---------------------------------------------------------------- events

EventRecorder::EventRecorder(const std::string& events_endpoint)
    : thread_([this, events_endpoint] { run(events_endpoint); }) {
  std::this_thread::sleep_for(300ms);  // PUB/SUB: subscribed before the first event counts
}

EventRecorder::~EventRecorder() {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
  }
  thread_.join();
}

void EventRecorder::run(std::string endpoint) {
  zmq::context_t context(1);
  zmq::socket_t sub(context, zmq::socket_type::sub);
  sub.set(zmq::sockopt::linger, 0);
  sub.set(zmq::sockopt::subscribe, "");
  sub.connect(endpoint);
  for (;;) {
    {
      std::lock_guard lock(mutex_);
      if (stop_) return;
    }
    std::optional<Message> event;
    try {
      event = transport::receive_event(sub, Limits::client_inbound(), 50ms);
    } catch (const std::exception&) {
      continue;
    }
    if (!event) continue;
    {
      std::lock_guard lock(mutex_);
      events_.push_back(std::move(*event));
      times_.push_back(std::chrono::steady_clock::now());
    }
    cv_.notify_all();
  }
}

std::optional<Message> EventRecorder::wait_for(const std::function<bool(const Message&)>& pred,
                                               std::chrono::milliseconds timeout) {
  std::unique_lock lock(mutex_);
  std::optional<Message> found;
  cv_.wait_for(lock, timeout, [&] {
    for (const auto& e : events_)
      if (pred(e)) {
        found = e;
        return true;
      }
    return false;
  });
  return found;
}

std::vector<Message> EventRecorder::snapshot() {
  std::lock_guard lock(mutex_);
  return events_;
}

std::vector<EventRecorder::Timed> EventRecorder::timed_snapshot() {
  std::lock_guard lock(mutex_);
  std::vector<Timed> out;
  for (std::size_t i = 0; i < events_.size(); ++i) out.emplace_back(times_[i], events_[i]);
  return out;
}

// ---------------------------------------------------------------- helpers

std::vector<ResultPart> all_result_parts() {
  return {ResultPart::kDisplacement, ResultPart::kDisplacementItk, ResultPart::kWarpedImage,
          ResultPart::kWarpedLabels, ResultPart::kModels,          ResultPart::kMetrics,
          ResultPart::kTimings,      ResultPart::kReport};
}

std::map<std::string, std::string> frames_by_name(const Message& reply) {
  throw_if_error(reply);
  std::map<std::string, std::string> out;
  for (const auto& f : parse_scan_result_reply(reply).frames) out[f.name] = f.bytes;
  return out;
}

std::map<std::string, std::string> pull_complete(Client& c, const std::string& scan_id,
                                                 const std::vector<ResultPart>& parts, std::chrono::seconds timeout) {
  const auto until = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    const Message reply = c.result(scan_id, parts);
    throw_if_error(reply);
    const ScanResultReply r = parse_scan_result_reply(reply);
    const bool pending = std::any_of(r.unavailable.begin(), r.unavailable.end(), [](const auto& u) { return u.pending; });
    if (!pending || std::chrono::steady_clock::now() > until) return frames_by_name(reply);
    std::this_thread::sleep_for(100ms);
  }
}

std::uint64_t resident_kib(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(in, line);)
    if (line.rfind("VmRSS:", 0) == 0) return std::stoull(line.substr(6));
  return 0;
}

std::size_t open_fds(pid_t pid) {
  std::size_t n = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator("/proc/" + std::to_string(pid) + "/fd")) ++n;
  return n;
}

std::vector<pid_t> child_pids(pid_t parent) {
  std::vector<pid_t> out;
  for (const auto& e : fs::directory_iterator("/proc")) {
    const std::string name = e.path().filename().string();
    if (name.find_first_not_of("0123456789") != std::string::npos) continue;
    std::ifstream in(e.path() / "stat");
    std::string stat;
    std::getline(in, stat);
    // pid (comm) state ppid ...: comm may hold spaces, so parse after the last ')'.
    const auto close = stat.rfind(')');
    if (close == std::string::npos) continue;
    std::istringstream rest(stat.substr(close + 1));
    std::string state;
    pid_t ppid = 0;
    rest >> state >> ppid;
    if (ppid == parent) out.push_back(static_cast<pid_t>(std::stoi(name)));
  }
  return out;
}

std::vector<ScanBytes> write_synthetic_inputs(const fs::path& dir, int count, double voxel_scale) {
  write_synthetic_preop(dir);
  std::vector<ScanBytes> scans;
  for (int i = 0; i < count; ++i) {
    // Distinct, plausible shifts of a few millimetres.
    const Eigen::Vector3d shift(2.0 + 0.7 * (i % 3), -1.5 + 0.8 * (i % 4), 1.0 + 0.5 * (i % 5));
    const std::string prefix = "scan" + std::to_string(i);
    write_synthetic_scan(dir, prefix, shift, voxel_scale);
    scans.push_back({read_file(dir / (prefix + "_labels.nii.gz")), read_file(dir / (prefix + "_t1.nii.gz"))});
  }
  return scans;
}

std::string test_config_text(int queue_depth) {
  return "[server]\npreop = \"none\"\nqueue_depth = " + std::to_string(queue_depth) +
         "\n\n[mesh]\ncell_size_mm = 7.0\nfacet_size_mm = 4.0\nfacet_distance_mm = 1.5\n";
}

}  // namespace brainshift::e2e
