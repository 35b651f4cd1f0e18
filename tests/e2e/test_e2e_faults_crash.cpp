// brainshiftd crashing, with real processes, sockets and files: kill -9 at
// several points of a scan's life, idempotent pushes across a crash, and a
// result served before it was written. Counts are printed as JSON for
// docs/reliability/faults.md.
#include <gtest/gtest.h>

#include <signal.h>

#include <cstdlib>
#include <map>
#include <optional>
#include <random>
#include <thread>

#include <nlohmann/json.hpp>

#include "fault_fixture.h"
#include "protocol/media.h"
#include "protocol/transport.h"

namespace brainshift::e2e {
namespace {

using namespace protocol;
using namespace std::chrono_literals;

std::size_t count_log(const std::string& log, const std::string& needle) {
  std::size_t n = 0;
  for (auto at = log.find(needle); at != std::string::npos; at = log.find(needle, at + 1)) ++n;
  return n;
}

// Kills the daemon (SIGKILL) and waits for it to be gone.
void kill9(Daemon& d) {
  d.process().signal(SIGKILL);
  ASSERT_TRUE(d.process().wait(30).has_value()) << "SIGKILL did not end the daemon";
}

// ---------------------------------------------------------------- kill -9

enum class KillPoint { during_push, random_after_ack, during_solve, during_result_write, during_deferred };
const char* to_string(KillPoint p) {
  switch (p) {
    case KillPoint::during_push: return "during_push";
    case KillPoint::random_after_ack: return "random_after_ack";
    case KillPoint::during_solve: return "during_solve";
    case KillPoint::during_result_write: return "during_result_write";
    case KillPoint::during_deferred: return "during_deferred";
  }
  return "?";
}

struct KillLedger {
  std::map<std::string, std::string> scan_by_client_id;             // every acknowledged push
  std::map<std::string, std::map<std::string, std::string>> frames;  // first seen bytes per finished scan
  std::size_t results_compared = 0;
};

// After a (re)start: every acknowledged scan is listed, no scan failed, and
// every finished result is byte-identical to what was pulled before the kills.
void verify_store(Client& c, KillLedger& ledger, bool all_finished) {
  const ScanListReply list = c.list();
  std::map<std::string, ScanSummary> listed;
  for (const auto& s : list.scans) listed[s.scan_id] = s;
  EXPECT_EQ(listed.size(), ledger.scan_by_client_id.size()) << "a scan appeared that was never acknowledged";
  for (const auto& [client_id, scan_id] : ledger.scan_by_client_id) {
    auto it = listed.find(scan_id);
    ASSERT_NE(it, listed.end()) << "acknowledged scan " << scan_id << " (" << client_id << ") lost";
    EXPECT_EQ(it->second.client_scan_id.value_or(""), client_id);
    EXPECT_NE(it->second.state, ScanState::kFailed)
        << scan_id << " failed: " << (it->second.error ? it->second.error->message : "");
    if (all_finished) {
      EXPECT_EQ(it->second.state, ScanState::kDone) << scan_id;
    }
    if (it->second.state != ScanState::kDone) continue;
    const auto frames = pull_complete(c, scan_id, all_result_parts());
    // The deferred outputs follow the result; a kill in between is repaired at start-up.
    for (ResultPart p : {ResultPart::kDisplacementItk, ResultPart::kMetrics, ResultPart::kReport})
      EXPECT_TRUE(frames.count(frame_name(p))) << scan_id << " has no " << frame_name(p);
    auto& known = ledger.frames[scan_id];
    for (const auto& [name, bytes] : known) {
      ASSERT_TRUE(frames.count(name)) << scan_id << ": " << name << " vanished after a kill";
      EXPECT_TRUE(frames.at(name) == bytes) << scan_id << ": " << name << " changed after a kill";
      ++ledger.results_compared;
    }
    for (const auto& [name, bytes] : frames) known.emplace(name, bytes);
  }
}

TEST(DaemonFaults, KillNineAtManyPointsLosesNoAcknowledgedScan) {
  const Inputs& in = inputs();
  const fs::path store = in.dir / "store-kill";
  const int rounds = std::getenv("BRAINSHIFT_KILL_ROUNDS") ? std::atoi(std::getenv("BRAINSHIFT_KILL_ROUNDS")) : 10;
  const unsigned seed = std::getenv("BRAINSHIFT_KILL_SEED") ? std::atoi(std::getenv("BRAINSHIFT_KILL_SEED")) : 20261122u;
  std::mt19937 random(seed);
  const KillPoint points[] = {KillPoint::during_result_write, KillPoint::during_deferred, KillPoint::random_after_ack,
                              KillPoint::during_solve, KillPoint::during_push};
  KillLedger ledger;
  std::map<std::string, int> kills_at;
  std::size_t leftovers_removed = 0, requeued = 0, itk_recovered = 0, deferred_repaired = 0, in_flight_stored = 0;
  std::optional<std::string> in_flight_client_id;
  int kills = 0, restarts = 0, busy_retries = 0;

  for (int round = 0; round <= rounds; ++round) {
    Daemon d(spec(store, "kill" + std::to_string(round)));
    restarts += round > 0;
    Client c(d.endpoint);
    if (round == 0) c.load_preop(in.preop_t1, in.preop_labels);
    ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
    // A push whose reply the kill swallowed: sending it again gives the one
    // scan (stored before the kill or not), never a second.
    if (in_flight_client_id) {
      const ScanBytes& s = in.scans[2];  // what the in-flight push carried
      const Message reply = push_retrying_busy(c, s, *in_flight_client_id, 300s, &busy_retries);
      throw_if_error(reply);
      const ScanPushReply again = parse_scan_push_reply(reply);
      in_flight_stored += again.duplicate;
      ledger.scan_by_client_id[*in_flight_client_id] = again.scan_id;
      in_flight_client_id.reset();
    }
    verify_store(c, ledger, false);
    if (round == rounds) {
      wait_all_finished(c, 600s);
      verify_store(c, ledger, true);
      EXPECT_TRUE(temporary_leftovers(store).empty());
      const std::string log = d.log();
      requeued += count_log(log, "re-queueing acknowledged scan");
      leftovers_removed += count_log(log, "removing an unfinished write");
      itk_recovered += count_log(log, "made again from field.nii");
      deferred_repaired += count_log(log, "made again by registering the stored scan again");
      d.process().signal(SIGTERM);
      EXPECT_EQ(d.process().wait(60).value_or(-1), 0) << d.log();
      break;
    }
    EventRecorder events(d.events);
    const KillPoint point = points[round % std::size(points)];
    std::vector<std::string> pushed;
    for (int i = 0; i < 3; ++i) {
      const ScanBytes& s = in.scans[i];
      const std::string client_id = "r" + std::to_string(round) + "-" + std::to_string(i);
      if (point == KillPoint::during_push && i == 2) {
        // Sent, not awaited: the kill lands while it is read, stored or answered.
        zmq::context_t ctx(1);
        zmq::socket_t raw(ctx, zmq::socket_type::dealer);
        raw.set(zmq::sockopt::linger, 0);
        raw.connect(d.endpoint);
        ScanPushRequest req{media::nifti_frame("labels", s.labels), media::nifti_frame("image", s.image), client_id};
        transport::send_request(raw, make_scan_push_request("inflight", req));
        std::this_thread::sleep_for(std::chrono::milliseconds(std::uniform_int_distribution<int>(0, 60)(random)));
        in_flight_client_id = client_id;
        break;
      }
      // Scans left queued by earlier kills are queued again on restart and can
      // fill the queue: then the push is refused (busy) and sent again.
      const std::string id = scan_id_of(push_retrying_busy(c, s, client_id, 300s, &busy_retries));
      ledger.scan_by_client_id[client_id] = id;
      pushed.push_back(id);
    }
    auto first_scan_event = [&](auto pred) {
      return events.wait_for(pred, 300s).has_value();
    };
    bool reached = true;
    switch (point) {
      case KillPoint::during_push: break;
      case KillPoint::random_after_ack:
        std::this_thread::sleep_for(std::chrono::milliseconds(std::uniform_int_distribution<int>(0, 2500)(random)));
        break;
      case KillPoint::during_solve:
        reached = first_scan_event([](const Message& m) { return progress_at(m, "solve", 0.0); });
        break;
      case KillPoint::during_result_write:
        // "outputs" done: the result is being written to the store now.
        reached = first_scan_event([](const Message& m) { return progress_at(m, "outputs", 1.0); });
        break;
      case KillPoint::during_deferred:
        // Announced done: field.h5 and report.png are being made and stored.
        reached = first_scan_event([&](const Message& m) {
          return is_scan_event(m, MessageType::kEventScanDone, pushed.front());
        });
        break;
    }
    ASSERT_TRUE(reached) << "kill point " << to_string(point) << " never reached: " << d.log();
    kill9(d);
    ++kills;
    ++kills_at[to_string(point)];
    const std::string log = d.log();
    requeued += count_log(log, "re-queueing acknowledged scan");
    leftovers_removed += count_log(log, "removing an unfinished write");
    itk_recovered += count_log(log, "made again from field.nii");
    deferred_repaired += count_log(log, "made again by registering the stored scan again");
  }
  std::size_t finished = 0;
  for (const auto& [id, frames] : ledger.frames) finished += !frames.empty();
  const json report{{"test", "kill9"},
                    {"seed", seed},
                    {"kills", kills},
                    {"kills_at", kills_at},
                    {"restarts", restarts + 1},
                    {"scans_acknowledged", ledger.scan_by_client_id.size()},
                    {"scans_finished", finished},
                    {"scans_lost", 0},
                    {"in_flight_pushes_found_stored_after_kill", in_flight_stored},
                    {"requeued_after_restart", requeued},
                    {"unfinished_writes_removed_on_open", leftovers_removed},
                    {"field_h5_remade_on_start", itk_recovered},
                    {"metrics_or_report_remade_on_start", deferred_repaired},
                    {"result_frames_compared_identical", ledger.results_compared},
                    {"pushes_refused_busy_and_retried", busy_retries}};
  std::printf("%s\n", report.dump().c_str());
}

// ---------------------------------------------------------------- idempotence

TEST(DaemonFaults, IdempotentPushHoldsAcrossAKill) {
  const Inputs& in = inputs();
  const fs::path store = in.dir / "store-idem";
  std::string scan_id;
  for (int life = 0; life < 2; ++life) {
    Daemon d(spec(store, "idem" + std::to_string(life)));
    Client c(d.endpoint);
    if (life == 0) c.load_preop(in.preop_t1, in.preop_labels);
    ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
    const ScanBytes &a = in.scans[0], &b = in.scans[1];
    const ScanPushReply first = parse_scan_push_reply(c.push(a.labels, a.image, "or-7/scan-1"));
    if (life == 0) {
      EXPECT_FALSE(first.duplicate);
      scan_id = first.scan_id;
    } else {
      EXPECT_TRUE(first.duplicate) << "after a kill -9 the same push is still the same scan";
    }
    EXPECT_EQ(first.scan_id, scan_id);
    const ScanPushReply again = parse_scan_push_reply(c.push(a.labels, a.image, "or-7/scan-1"));
    EXPECT_TRUE(again.duplicate);
    EXPECT_EQ(again.scan_id, scan_id);
    // Same id, other bytes (here: the other scan; also: labels without the image).
    for (const auto& other : {c.push(b.labels, b.image, "or-7/scan-1"), c.push(a.labels, "", "or-7/scan-1")}) {
      ASSERT_EQ(other.type(), MessageType::kError);
      const ErrorInfo e = parse_error_reply(other);
      EXPECT_EQ(e.code, ErrorCode::kConflict);
      EXPECT_NE(e.message.find(scan_id), std::string::npos) << e.message;
    }
    const ScanListReply list = c.list();
    ASSERT_EQ(list.scans.size(), 1u) << "no duplicate scan was stored";
    EXPECT_EQ(list.scans[0].scan_id, scan_id);
    kill9(d);
  }
}

// ---------------------------------------------------------------- served before written

// A result is announced and served before the store has it (the store's
// fsync is off the latency path). That is safe only because the scan itself
// is durable from its acknowledgement: a crash before the write must leave
// the scan acknowledged without a result, and the restart must compute the
// same result again. The fault switch keeps the first result from ever being
// written, so the kill lands in that window every time.
TEST(DaemonFaults, ResultServedBeforeItIsWrittenIsComputedAgainAfterACrash) {
  const Inputs& in = inputs();
  const fs::path store = in.dir / "store-unwritten";
  const ScanBytes& s = in.scans[0];
  const std::vector<ResultPart> parts{ResultPart::kDisplacement, ResultPart::kWarpedImage, ResultPart::kWarpedLabels,
                                      ResultPart::kModels, ResultPart::kTimings};
  std::string scan_id;
  std::map<std::string, std::string> served;
  {
    DaemonSpec first = spec(store, "unwritten0");
    first.env = {"BRAINSHIFT_INJECT_FAULT=result_write@0#1"};
    Daemon d(first);
    Client c(d.endpoint);
    c.load_preop(in.preop_t1, in.preop_labels);
    ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
    EventRecorder events(d.events);
    scan_id = scan_id_of(c.push(s.labels, s.image, "unwritten-1"));
    ASSERT_TRUE(events.wait_for([&](const Message& m) { return is_scan_event(m, MessageType::kEventScanDone, scan_id); },
                                300s))
        << d.log();
    const Message reply = c.result(scan_id, parts);
    throw_if_error(reply);
    served = frames_by_name(reply);
    EXPECT_TRUE(served.count(frame_name(ResultPart::kDisplacement))) << "the field is served from memory";
    EXPECT_TRUE(served.count(frame_name(ResultPart::kWarpedLabels)));
    const ScanListReply list = c.list();
    ASSERT_EQ(list.scans.size(), 1u);
    EXPECT_EQ(list.scans[0].state, ScanState::kDone);
    EXPECT_FALSE(fs::exists(store / "scans" / scan_id / "result.h5")) << "the result must not be on disk yet";
    EXPECT_NE(d.log().find("never written"), std::string::npos) << d.log();
    kill9(d);
  }
  Daemon d(spec(store, "unwritten1"));
  Client c(d.endpoint);
  ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
  const ScanListReply list = wait_all_finished(c, 600s);
  ASSERT_EQ(list.scans.size(), 1u) << "the acknowledged scan is still there";
  EXPECT_EQ(list.scans[0].state, ScanState::kDone);
  EXPECT_NE(d.log().find("re-queueing acknowledged scan " + scan_id), std::string::npos) << d.log();
  EXPECT_TRUE(fs::exists(store / "scans" / scan_id / "result.h5"));
  const auto again = pull_complete(c, scan_id, all_result_parts());
  std::size_t compared = 0;
  for (const auto& [name, bytes] : served) {
    if (name == frame_name(ResultPart::kTimings)) continue;  // this run's seconds, not the first run's
    ASSERT_TRUE(again.count(name)) << name << " missing after the restart";
    EXPECT_TRUE(again.at(name) == bytes) << name << " differs from what was served before the crash";
    ++compared;
  }
  EXPECT_GE(compared, 4u);
  std::printf("%s\n", json{{"test", "served_before_written"}, {"frames_compared_identical", compared}}.dump().c_str());
  d.process().signal(SIGTERM);
  EXPECT_EQ(d.process().wait(60).value_or(-1), 0) << d.log();
}

}  // namespace
}  // namespace brainshift::e2e
