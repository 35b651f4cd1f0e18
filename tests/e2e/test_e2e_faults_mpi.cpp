// brainshiftd under mpirun -np 2 when a rank fails: an injected failure of
// rank 1's solve, and SIGKILL of rank 1 while a scan runs, then a restart on
// the same store. Counts are printed as JSON for docs/reliability/faults.md.
#include <gtest/gtest.h>

#include <signal.h>

#include <fstream>
#include <map>
#include <thread>

#include <nlohmann/json.hpp>

#include "fault_fixture.h"

namespace brainshift::e2e {
namespace {

using namespace protocol;
using namespace std::chrono_literals;

// ---------------------------------------------------------------- MPI ranks

// True once pid has exited (gone, or a zombie waiting for its reaper).
bool gone_within(pid_t pid, std::chrono::seconds timeout) {
  const auto until = std::chrono::steady_clock::now() + timeout;
  do {
    std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
    std::string stat;
    if (!std::getline(in, stat)) return true;
    const auto close = stat.rfind(')');
    if (close != std::string::npos && stat.size() > close + 2 && stat[close + 2] == 'Z') return true;
    std::this_thread::sleep_for(100ms);
  } while (std::chrono::steady_clock::now() < until);
  return false;
}

TEST(DaemonFaults, FailureOnRankOneIsReportedAndKillingItEndsTheJob) {
  const Inputs& in = inputs();
  const fs::path store = in.dir / "store-mpi";
  std::map<std::string, std::map<std::string, std::string>> before;
  std::string in_flight;
  {
    DaemonSpec s = spec(store, "mpi-fault", 2);
    s.env = {"BRAINSHIFT_INJECT_FAULT=solve@1#1"};  // rank 1's first solve throws
    Daemon d(s);
    Client c(d.endpoint);
    c.load_preop(in.preop_t1, in.preop_labels);
    ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
    EventRecorder events(d.events);
    std::vector<std::string> ids;
    for (int i = 0; i < 2; ++i) {
      ids.push_back(scan_id_of(c.push(in.scans[i].labels, in.scans[i].image, "mpi-" + std::to_string(i))));
      ASSERT_TRUE(events.wait_for([&](const Message& m) { return is_scan_event(m, MessageType::kEventScanDone, ids.back()); }, 300s))
          << "the scan did not finish: the ranks disagree or hang\n" << d.log();
    }
    // Scan 0: rank 1 failed its solve; every rank agreed, and the result is
    // the clearly marked affine-only fallback naming the failing rank.
    const json m0 = json::parse(pull_complete(c, ids[0], {ResultPart::kMetrics}).at(frame_name(ResultPart::kMetrics)));
    EXPECT_EQ(m0.at("result"), "affine_only_fallback");
    const std::string reason = m0.value("fallback_reason", "");
    EXPECT_NE(reason.find("rank 1"), std::string::npos) << reason;
    EXPECT_NE(reason.find("injected fault"), std::string::npos) << reason;
    std::printf("scan after a rank-1 solve failure: %s\n", reason.c_str());
    // Scan 1: the next solve works on every rank.
    const json m1 = json::parse(pull_complete(c, ids[1], {ResultPart::kMetrics}).at(frame_name(ResultPart::kMetrics)));
    EXPECT_EQ(m1.at("result"), "nonrigid");
    for (const auto& id : ids) before[id] = pull_complete(c, id, all_result_parts());

    // SIGKILL of rank 1 while a scan runs: mpirun ends the whole job.
    in_flight = scan_id_of(c.push(in.scans[2].labels, in.scans[2].image, "mpi-2"));
    ASSERT_TRUE(events.wait_for([](const Message& m) { return progress_at(m, "affine", 0.0); }, 300s));
    std::vector<pid_t> ranks = child_pids(d.process().pid());
    pid_t rank1 = -1;
    for (pid_t p : ranks)
      if (p != d.rank0_pid()) rank1 = p;
    ASSERT_GT(rank1, 0) << "rank 1 not found among mpirun's children";
    const auto t_kill = std::chrono::steady_clock::now();
    ::kill(rank1, SIGKILL);
    const auto code = d.process().wait(120);
    const double end_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_kill).count();
    if (!code) ::kill(d.rank0_pid(), SIGKILL);
    ASSERT_TRUE(code.has_value()) << "mpirun did not end after rank 1 was killed";
    EXPECT_NE(*code, 0);
    EXPECT_TRUE(gone_within(d.rank0_pid(), 30s)) << "rank 0 survived its job";
    std::printf("%s\n", json{{"test", "mpi_rank_faults"}, {"injected_rank1_solve_failures", 1},
                             {"rank1_sigkills", 1}, {"mpirun_exit_code", *code},
                             {"seconds_from_rank1_kill_to_job_end", end_seconds}}
                            .dump()
                            .c_str());
  }
  // Restart on the same store: the in-flight scan is processed, the others unchanged.
  Daemon d(spec(store, "mpi-restart", 2));
  Client c(d.endpoint);
  ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
  const ScanListReply list = wait_all_finished(c, 600s);
  ASSERT_EQ(list.scans.size(), 3u);
  for (const auto& s : list.scans) EXPECT_EQ(s.state, ScanState::kDone) << s.scan_id;
  for (const auto& [id, frames] : before) {
    const auto now = pull_complete(c, id, all_result_parts());
    for (const auto& [name, bytes] : frames) EXPECT_TRUE(now.count(name) && now.at(name) == bytes) << id << " " << name;
  }
  EXPECT_EQ(frames_by_name(c.result(in_flight, {ResultPart::kDisplacement})).size(), 1u);
  // SIGTERM to rank 0 (mpirun would report a forwarded signal as a failure).
  ::kill(d.rank0_pid(), SIGTERM);
  EXPECT_EQ(d.process().wait(120).value_or(-1), 0) << d.log();
}

}  // namespace
}  // namespace brainshift::e2e
