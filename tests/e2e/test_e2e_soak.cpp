// The bounded soak: 200 scans pushed back to back to a real brainshiftd while
// a puller and a watcher run. Every scan must get a result (pushes refused
// with `busy` are counted and retried); the daemon's resident memory after
// the first 20 scans may grow by less than 5 % to the end, and its open file
// descriptors (sockets included) must not grow. Throughput and latency are
// printed as JSON; no assertion on speed (that is the benchmarks' business).
//
// BRAINSHIFT_SOAK_SCANS (default 200) and BRAINSHIFT_SOAK_RANKS (default 1;
// 2 runs it under mpirun -np 2) change the run for a manual soak.
#include <gtest/gtest.h>

#include <signal.h>

#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <fstream>
#include <set>
#include <thread>

#include <nlohmann/json.hpp>

#include "daemon_harness.h"
#include "temp_dir.h"  // tests/support

using namespace brainshift;
using namespace brainshift::e2e;
using namespace brainshift::protocol;
using namespace std::chrono_literals;
namespace fs = std::filesystem;
using nlohmann::json;
using Clock = std::chrono::steady_clock;

namespace {

int env_int(const char* name, int fallback) {
  const char* v = std::getenv(name);
  return v && *v ? std::atoi(v) : fallback;
}

double seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

json percentiles(std::vector<double> v) {
  if (v.empty()) return json::object();
  std::sort(v.begin(), v.end());
  auto at = [&](double q) { return v[std::min(v.size() - 1, static_cast<std::size_t>(q * (v.size() - 1) + 0.5))]; };
  return {{"p50", at(0.50)}, {"p95", at(0.95)}, {"max", v.back()}, {"n", v.size()}};
}

std::size_t count_finished(EventRecorder& events) {
  std::size_t n = 0;
  for (const auto& m : events.snapshot())
    n += m.type() == MessageType::kEventScanDone || m.type() == MessageType::kEventScanFailed;
  return n;
}

struct Sample {
  std::size_t scans_finished;
  std::uint64_t rss_kib;
  std::size_t fds;
};

TEST(DaemonSoak, TwoHundredScansBackToBack) {
  const int total = env_int("BRAINSHIFT_SOAK_SCANS", 200);
  const int ranks = env_int("BRAINSHIFT_SOAK_RANKS", 1);
  test::TempDir tmp("soak");
  const fs::path dir = tmp.path();
  const fs::path config = dir / "soak.toml";
  // Resident memory is compared at idle, after the daemon has returned its
  // free heap pages (idle_release_ms): while scans run, the heap's high-water
  // mark moves in steps of a few MB with fragmentation, which says nothing
  // about memory being kept.
  constexpr auto kIdleRelease = 500ms;
  std::string config_text = test_config_text(4);
  config_text.insert(config_text.find("[server]\n") + 9, "idle_release_ms = 500\n");
  std::ofstream(config) << config_text;
  // Voxels twice as large: the same head, an eighth of the result bytes.
  const std::vector<ScanBytes> scans = write_synthetic_inputs(dir, 4, 2.0);

  Daemon d(DaemonSpec{dir, config, dir / "store", "soak", ranks > 1 ? ranks : 0, {}, {}});
  const pid_t pid = d.rank0_pid();
  Client pusher(d.endpoint);
  pusher.load_preop(read_file(dir / "preop_t1.nii.gz"), read_file(dir / "preop_labels.nii.gz"));
  ASSERT_NO_THROW(pusher.wait_ready(300s)) << d.log();

  EventRecorder watcher(d.events);
  std::atomic<bool> stop{false};
  std::atomic<int> pulls{0}, pull_errors{0};
  // The puller fetches each finished scan's field, metrics and models once.
  std::thread puller([&] {
    Client c(d.endpoint);
    std::set<std::string> pulled;
    while (!stop) {
      for (const auto& s : c.list(50).scans) {
        if (s.state != ScanState::kDone || pulled.count(s.scan_id)) continue;
        const auto frames =
            pull_complete(c, s.scan_id, {ResultPart::kDisplacement, ResultPart::kMetrics, ResultPart::kModels});
        if (frames.count(frame_name(ResultPart::kDisplacement)) && frames.count(frame_name(ResultPart::kMetrics)))
          ++pulls;
        else
          ++pull_errors;
        pulled.insert(s.scan_id);
      }
      std::this_thread::sleep_for(100ms);
    }
  });

  std::vector<Sample> samples;
  std::optional<Sample> after_20;
  std::map<std::string, Clock::time_point> acked_at;
  std::vector<double> push_seconds;
  int busy = 0, push_errors = 0;
  const auto t0 = Clock::now();
  for (int i = 0; i < total; ++i) {
    for (;;) {
      const auto t = Clock::now();
      const Message reply = pusher.push(scans[i % scans.size()].labels, scans[i % scans.size()].image,
                                        "soak-" + std::to_string(i));
      if (reply.type() == MessageType::kError) {
        const ErrorInfo e = parse_error_reply(reply);
        if (e.code == ErrorCode::kBusy) {
          ++busy;
          std::this_thread::sleep_for(50ms);
          continue;
        }
        ++push_errors;
        ADD_FAILURE() << "push " << i << ": " << to_string(e.code) << ": " << e.message;
        break;
      }
      push_seconds.push_back(seconds(Clock::now() - t));
      acked_at[parse_scan_push_reply(reply).scan_id] = Clock::now();
      break;
    }
    const std::size_t finished = count_finished(watcher);
    if (!after_20 && finished >= 20) {
      // Let the queue drain and the daemon go idle, then take the reference.
      while (count_finished(watcher) < acked_at.size()) std::this_thread::sleep_for(50ms);
      std::this_thread::sleep_for(kIdleRelease + 1s);
      after_20 = Sample{count_finished(watcher), resident_kib(pid), open_fds(pid)};
      samples.push_back(*after_20);
    } else if (after_20 && finished >= samples.back().scans_finished + 20) {
      samples.push_back(Sample{finished, resident_kib(pid), open_fds(pid)});
    }
  }
  // Every acknowledged scan finishes.
  const auto until = Clock::now() + 600s;
  while (count_finished(watcher) < acked_at.size() && Clock::now() < until) std::this_thread::sleep_for(100ms);
  const auto t_end = Clock::now();
  // The last report.png, the puller's last round, and the idle release.
  std::this_thread::sleep_for(kIdleRelease + 1s);
  stop = true;
  puller.join();

  std::vector<double> latency;
  std::size_t done = 0, failed = 0;
  std::set<std::string> finished_ids;
  for (const auto& [t, m] : watcher.timed_snapshot()) {
    std::string id;
    if (m.type() == MessageType::kEventScanDone) {
      id = parse_scan_done_event(m).scan_id;
      ++done;
    } else if (m.type() == MessageType::kEventScanFailed) {
      const auto f = parse_scan_failed_event(m);
      id = f.scan_id;
      ++failed;
      ADD_FAILURE() << id << " failed: " << f.error.message;
    } else {
      continue;
    }
    finished_ids.insert(id);
    if (auto it = acked_at.find(id); it != acked_at.end()) latency.push_back(seconds(t - it->second));
  }
  const Sample end{done + failed, resident_kib(pid), open_fds(pid)};
  samples.push_back(end);

  EXPECT_EQ(acked_at.size(), static_cast<std::size_t>(total)) << "every push was acknowledged (after busy retries)";
  EXPECT_EQ(done, static_cast<std::size_t>(total));
  EXPECT_EQ(failed, 0u);
  EXPECT_EQ(pull_errors.load(), 0);
  const ScanListReply list = pusher.list();
  EXPECT_EQ(list.scans.size(), static_cast<std::size_t>(total));
  for (const auto& s : list.scans) EXPECT_EQ(s.state, ScanState::kDone) << s.scan_id;
  ASSERT_TRUE(after_20.has_value());
  EXPECT_LT(static_cast<double>(end.rss_kib), 1.05 * static_cast<double>(after_20->rss_kib))
      << "resident memory grew by 5 % or more after the first 20 scans";
  EXPECT_LE(end.fds, after_20->fds) << "file descriptors leaked";

  json series = json::array();
  for (const auto& s : samples) series.push_back({{"scans", s.scans_finished}, {"rss_kib", s.rss_kib}, {"fds", s.fds}});
  const double wall = seconds(t_end - t0);
  const json report{{"test", "soak"},
                    {"mpi_ranks", ranks},
                    {"scans_pushed", total},
                    {"scans_acknowledged", acked_at.size()},
                    {"scans_done", done},
                    {"scans_failed", failed},
                    {"scans_lost", acked_at.size() - finished_ids.size()},
                    {"busy_replies_retried", busy},
                    {"push_errors", push_errors},
                    {"results_pulled", pulls.load()},
                    {"wall_seconds", wall},
                    {"throughput_scans_per_s", total / wall},
                    {"push_ack_seconds", percentiles(push_seconds)},
                    {"ack_to_done_seconds", percentiles(latency)},
                    {"rss_kib_after_20", after_20->rss_kib},
                    {"rss_kib_end", end.rss_kib},
                    {"rss_growth_percent", 100.0 * (double(end.rss_kib) / double(after_20->rss_kib) - 1.0)},
                    {"fds_after_20", after_20->fds},
                    {"fds_end", end.fds},
                    {"series", series}};
  std::printf("%s\n", report.dump().c_str());

  // SIGTERM to rank 0 (under mpirun, a signal to mpirun itself is reported as a failure).
  ::kill(pid, SIGTERM);
  EXPECT_EQ(d.process().wait(120).value_or(-1), 0) << d.log();
  if (::testing::Test::HasFailure()) tmp.keep();
}

}  // namespace
