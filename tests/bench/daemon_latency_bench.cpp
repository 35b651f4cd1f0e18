// Latency of a running brainshiftd as the scanner sees it (issues 4 and 12):
//   * preop.load of the default atlas: request sent -> event.preop.ready;
//   * per scan, pushed one at a time once the server is idle again (OR scans
//     come minutes apart; the deferred outputs after scan.done are therefore
//     never in the way of the next scan), p50/p95 over --scans scans:
//     with --client, the user's command `brainshift push --labels L --image I
//     --wait` (without --labels: an image alone, the daemon segments it) from
//     its start to its exit (client_push_wait_s), and, from the
//     same start, this benchmark's own receipt of event.scan.done
//     (client_start_to_done_event_s); without it, scan.push sent by this
//     process -> event.scan.done received (push_to_result_ready_s);
//   * the daemon's own stage timings (from event.stage): p50 per line
//     (stage_p50_s) and p50 over scans of each stage's sum (stage_per_scan);
//   * resident memory (VmRSS, and the peak VmHWM) of the given daemon
//     processes after the scans;
//   * with --restarted-at: a daemon restarted (after kill -9) at that time
//     (ns since the epoch): seconds until it is ready (warm, state ready) and
//     until every acknowledged scan is processed (no scan queued or running).
// Prints one JSON object. Driven by daemon_latency_bench.sh, which starts the
// daemon (np 1 or 2) and makes the phantom scan.
#include <algorithm>
#include <cmath>
#include <chrono>
#include <cstring>
#include <fstream>
#include <optional>
#include <iostream>
#include <map>
#include <sstream>
#include <thread>

#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <zmq.hpp>

#include "protocol/events.h"
#include "protocol/media.h"
#include "protocol/requests.h"
#include "protocol/transport.h"

namespace {
using namespace brainshift::protocol;
using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;
namespace transport = brainshift::protocol::transport;

double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path + ": cannot open");
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// Nearest-rank percentile.
double percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const auto rank = static_cast<std::size_t>(std::ceil(p / 100.0 * static_cast<double>(v.size())));
  return v[std::clamp<std::size_t>(rank, 1, v.size()) - 1];
}

nlohmann::json summary(const std::vector<double>& v) {
  return {{"p50", percentile(v, 50)}, {"p95", percentile(v, 95)},
          {"min", v.empty() ? 0.0 : *std::min_element(v.begin(), v.end())},
          {"max", v.empty() ? 0.0 : *std::max_element(v.begin(), v.end())}, {"n", v.size()}};
}

// A field of /proc/<pid>/status in KiB (VmRSS now, VmHWM the peak), -1 if gone.
long status_kib(int pid, const std::string& field) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(in, line);)
    if (line.rfind(field + ":", 0) == 0) return std::stol(line.substr(field.size() + 1));
  return -1;
}

extern "C" char** environ;

// Starts argv (stdout and stderr to /dev/null, as a script would discard them).
pid_t spawn(const std::vector<std::string>& argv) {
  std::vector<char*> args;
  for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 2, "/dev/null", O_WRONLY, 0);
  pid_t pid = -1;
  const int rc = posix_spawn(&pid, args[0], &actions, nullptr, args.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  if (rc != 0) throw std::runtime_error(argv[0] + ": cannot start: " + std::strerror(rc));
  return pid;
}

// Exit code once the child ended, nullopt while it runs.
std::optional<int> exited(pid_t pid) {
  int status = 0;
  if (::waitpid(pid, &status, WNOHANG) != pid) return std::nullopt;
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
}

class Bench {
 public:
  Bench(const std::string& server, const std::string& events)
      : dealer_(ctx_, zmq::socket_type::dealer), sub_(ctx_, zmq::socket_type::sub) {
    dealer_.set(zmq::sockopt::linger, 0);
    dealer_.connect(server);
    sub_.set(zmq::sockopt::subscribe, "event.");
    sub_.connect(events);
    std::this_thread::sleep_for(300ms);  // let the subscription reach the PUB
  }

  Message call(const Message& request) {
    transport::send_request(dealer_, request);
    for (;;) {
      auto reply = transport::receive_reply(dealer_, Limits::client_inbound(), 120s);
      if (!reply) throw std::runtime_error("no reply from the daemon within 120 s");
      if (reply->request_id() == request.request_id()) return *reply;
    }
  }
  std::string rid() { return "bench-" + std::to_string(++counter_); }

  // Waits for an event accepted by `done` (returns true to stop); stage
  // events are collected on the way.
  // One event within `wait` (recorded), or nullopt.
  std::optional<Message> next_event(std::chrono::milliseconds wait) {
    auto e = transport::receive_event(sub_, Limits::client_inbound(), wait);
    if (e) record(*e);
    return e;
  }

  template <class Done>
  void wait_event(Done&& done, std::chrono::seconds limit) {
    const auto deadline = Clock::now() + limit;
    while (Clock::now() < deadline) {
      auto e = transport::receive_event(sub_, Limits::client_inbound(), 100ms);
      if (!e) continue;
      record(*e);
      if (done(*e)) return;
    }
    throw std::runtime_error("timed out waiting for an event");
  }

  void wait_idle() {
    for (int i = 0; i < 600; ++i) {
      const StatusReply s = parse_status_reply(call(make_status_request(rid())));
      if (s.state == ServerState::kReady && s.queue.depth == 0) return;
      std::this_thread::sleep_for(50ms);
      drain_events();
    }
    throw std::runtime_error("the daemon did not become idle");
  }
  void drain_events() {
    while (auto e = transport::receive_event(sub_, Limits::client_inbound(), 0ms)) record(*e);
  }
  void record(const Message& e) {
    if (e.type() != MessageType::kEventStage) return;
    const StageTiming t = parse_stage_event(e).timing;
    if (t.scope == StageScope::kIntraop) {
      stages_[t.stage].push_back(t.seconds);
      auto& per_scan = scan_stages_[t.scan_id][t.stage];
      per_scan.first += t.seconds;
      ++per_scan.second;
    } else {
      preop_stages_[t.stage] = t.seconds;
    }
  }

  std::map<std::string, std::vector<double>> stages_;
  // Per scan and stage: the seconds of all its lines, and how many. A stage
  // runs once per pass (an image-only scan makes two: the light pass for the
  // re-match's prior and the answer's; the segmentation a line per round),
  // so a line's p50 is not what the stage costs a scan.
  std::map<std::string, std::map<std::string, std::pair<double, int>>> scan_stages_;
  std::map<std::string, double> preop_stages_;

 private:
  zmq::context_t ctx_;
  zmq::socket_t dealer_, sub_;
  unsigned counter_ = 0;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"brainshiftd push-to-result latency benchmark (prints JSON)"};
  std::string server, events, labels_path, image_path, client;
  int scans = 20;
  bool load_preop = false;
  std::vector<int> pids;
  app.add_option("--server", server, "request endpoint")->required();
  app.add_option("--events", events, "event endpoint")->required();
  app.add_option("--labels", labels_path, "intraop labels NIfTI (as the scanner sends it); none: the image alone");
  app.add_option("--image", image_path, "intraop T1 NIfTI");
  app.add_option("--scans", scans, "scans to push");
  app.add_flag("--load-preop", load_preop, "send preop.load (default atlas) first and time the warm-up");
  std::int64_t restarted_at_ns = 0;
  app.add_option("--restarted-at", restarted_at_ns, "time a restarted daemon: ns since the epoch of its launch");
  app.add_option("--client", client, "the brainshift CLI: time `brainshift push --wait` as the user runs it");
  app.add_option("--pids", pids, "daemon processes (every MPI rank) whose VmRSS is reported")->delimiter(',');
  CLI11_PARSE(app, argc, argv);
  if (labels_path.empty() && image_path.empty()) {
    std::cerr << "give --labels, --image or both\n";
    return 2;
  }

  try {
    if (restarted_at_ns > 0) {
      Bench b(server, events);
      const auto epoch_s = [restarted_at_ns] {
        const auto now = std::chrono::system_clock::now().time_since_epoch();
        return std::chrono::duration<double>(now).count() - restarted_at_ns * 1e-9;
      };
      nlohmann::json out;
      for (;; std::this_thread::sleep_for(20ms)) {
        const StatusReply st = parse_status_reply(b.call(make_status_request(b.rid())));
        if (st.state == ServerState::kReady || st.state == ServerState::kProcessing) {
          out["restart_to_ready_s"] = epoch_s();
          if (st.mesh) out["mesh"] = {{"nodes", st.mesh->nodes}, {"tets", st.mesh->tets}};
          break;
        }
        if (epoch_s() > 600) throw std::runtime_error("the restarted daemon was not ready within 600 s");
      }
      std::size_t scans_listed = 0;
      for (;; std::this_thread::sleep_for(50ms)) {
        const ScanListReply list = parse_scan_list_reply(b.call(make_scan_list_request(b.rid(), {kMaxScanListLimit})));
        bool busy = false;
        for (const auto& sc : list.scans) busy |= sc.state == ScanState::kQueued || sc.state == ScanState::kProcessing;
        scans_listed = list.scans.size();
        if (!busy) break;
        if (epoch_s() > 900) throw std::runtime_error("acknowledged scans not processed within 900 s");
      }
      out["restart_to_all_scans_processed_s"] = epoch_s();
      out["scans_listed"] = scans_listed;
      out["preop_stages_s"] = b.preop_stages_;
      std::cout << out.dump(2) << '\n';
      return 0;
    }
    Bench b(server, events);
    nlohmann::json out;
    out["scans"] = scans;
    out["input"] = labels_path.empty() ? "image_only" : image_path.empty() ? "labels_only" : "labels_and_image";
    if (load_preop) {
      PreopLoadRequest r;
      r.use_default_atlas = true;
      const auto t0 = Clock::now();
      const std::string id = parse_preop_load_reply(b.call(make_preop_load_request(b.rid(), r))).preop_id;
      double server_seconds = 0;
      MeshSize mesh;
      b.wait_event(
          [&](const Message& e) {
            if (e.type() == MessageType::kEventPreopFailed) throw std::runtime_error("preop.load failed");
            if (e.type() != MessageType::kEventPreopReady) return false;
            const auto ready = parse_preop_ready_event(e);
            server_seconds = ready.seconds;
            mesh = ready.mesh;
            return ready.preop_id == id;
          },
          1800s);
      out["preop_load"] = {{"wall_s", since(t0)}, {"server_s", server_seconds}, {"stages_s", b.preop_stages_}};
      out["mesh"] = {{"nodes", mesh.nodes}, {"tets", mesh.tets}};
    }
    b.wait_idle();
    const StatusReply status = parse_status_reply(b.call(make_status_request(b.rid())));
    out["mpi_ranks"] = status.mpi_ranks;
    if (status.mesh) out["mesh"] = {{"nodes", status.mesh->nodes}, {"tets", status.mesh->tets}};

    std::vector<double> latency, ack, server_total, client_wait, client_to_event;
    b.stages_.clear();
    b.scan_stages_.clear();
    if (client.empty()) {
      ScanPushRequest push;
      if (!labels_path.empty()) push.labels = media::nifti_frame("labels", read_file(labels_path));
      if (!image_path.empty()) push.image = media::nifti_frame("image", read_file(image_path));
      for (int i = 0; i < scans; ++i) {
        b.wait_idle();
        const auto t0 = Clock::now();
        const ScanPushReply reply = parse_scan_push_reply(b.call(make_scan_push_request(b.rid(), push)));
        ack.push_back(since(t0));
        b.wait_event(
            [&](const Message& e) {
              if (e.type() == MessageType::kEventScanFailed && parse_scan_failed_event(e).scan_id == reply.scan_id)
                throw std::runtime_error(reply.scan_id + " failed");
              if (e.type() != MessageType::kEventScanDone) return false;
              const auto done = parse_scan_done_event(e);
              if (done.scan_id != reply.scan_id) return false;
              latency.push_back(since(t0));
              server_total.push_back(done.seconds);
              return true;
            },
            600s);
        std::cerr << reply.scan_id << ": " << latency.back() << " s\n";
      }
    } else {
      std::vector<std::string> argv{client, "--server", server, "--events", events, "push"};
      if (!labels_path.empty()) argv.insert(argv.end(), {"--labels", labels_path});
      if (!image_path.empty()) argv.insert(argv.end(), {"--image", image_path});
      argv.push_back("--wait");
      for (int i = 0; i < scans; ++i) {
        b.wait_idle();
        b.drain_events();
        const auto t0 = Clock::now();
        const pid_t pid = spawn(argv);
        std::optional<int> code;
        std::optional<double> done_at;
        while (!(code = exited(pid))) {
          if (since(t0) > 600) throw std::runtime_error("brainshift push --wait did not end within 600 s");
          auto e = b.next_event(5ms);
          if (!e || done_at) continue;
          if (e->type() == MessageType::kEventScanDone) {
            done_at = since(t0);
            server_total.push_back(parse_scan_done_event(*e).seconds);
          } else if (e->type() == MessageType::kEventScanFailed) {
            throw std::runtime_error("a scan failed: " + parse_scan_failed_event(*e).error.message);
          }
        }
        if (*code != 0) throw std::runtime_error("brainshift push --wait exited with " + std::to_string(*code));
        client_wait.push_back(since(t0));
        if (done_at) client_to_event.push_back(*done_at);
        std::cerr << "scan " << i + 1 << ": client " << client_wait.back() << " s, scan.done at "
                  << done_at.value_or(-1) << " s\n";
      }
    }
    b.wait_idle();  // report.png of the last scan, so its stage is counted too
    if (client.empty()) {
      out["push_to_result_ready_s"] = summary(latency);
      out["push_ack_s"] = summary(ack);
    } else {
      out["client_push_wait_s"] = summary(client_wait);
      out["client_start_to_done_event_s"] = summary(client_to_event);
    }
    out["server_scan_total_s"] = summary(server_total);
    nlohmann::json stages;
    for (const auto& [name, v] : b.stages_) stages[name] = percentile(v, 50);
    out["stage_p50_s"] = stages;
    std::map<std::string, std::vector<double>> per_scan, lines;
    for (const auto& [scan, by_stage] : b.scan_stages_)
      for (const auto& [name, sum_count] : by_stage) {
        per_scan[name].push_back(sum_count.first);
        lines[name].push_back(sum_count.second);
      }
    nlohmann::json scan_stages;
    for (const auto& [name, v] : per_scan)
      scan_stages[name] = {{"p50_s", percentile(v, 50)}, {"lines_p50", percentile(lines[name], 50)}};
    out["stage_per_scan"] = scan_stages;
    nlohmann::json rss = nlohmann::json::array();
    for (int pid : pids)
      rss.push_back({{"pid", pid}, {"vm_rss_kib", status_kib(pid, "VmRSS")}, {"vm_hwm_kib", status_kib(pid, "VmHWM")}});
    out["rss_after_scans"] = rss;
    std::cout << out.dump(2) << '\n';
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "daemon_latency_bench: " << e.what() << '\n';
    return 1;
  }
}
