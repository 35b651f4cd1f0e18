// brainshiftd under faults, with real processes, sockets and files:
// kill -9 at several points of a scan's life, clients that vanish or never
// read, idempotent pushes across a crash, a store that refuses writes (a
// file-size limit on the daemon; a full tmpfs when mounting is permitted),
// and a failing or killed MPI rank. Counts are printed as JSON for
// docs/reliability/faults.md.
#include <gtest/gtest.h>

#include <netinet/in.h>
#include <signal.h>
#include <sys/mount.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cstdlib>
#include <memory>
#include <fstream>
#include <random>
#include <set>
#include <thread>

#include <nlohmann/json.hpp>

#include "daemon_harness.h"
#include "protocol/media.h"
#include "protocol/transport.h"
#include "temp_dir.h"  // tests/support

using namespace brainshift;
using namespace brainshift::e2e;
using namespace brainshift::protocol;
using namespace std::chrono_literals;
namespace fs = std::filesystem;
using nlohmann::json;

namespace {

struct Inputs {
  test::TempDir tmp{"faults"};
  fs::path dir = tmp.path();
  fs::path config;
  std::string preop_t1, preop_labels;
  std::vector<ScanBytes> scans;
};

std::unique_ptr<Inputs> g_inputs;

// Made once for all tests (the synthetic images take a moment).
Inputs& inputs() {
  if (!g_inputs) {
    g_inputs = std::make_unique<Inputs>();
    Inputs* i = g_inputs.get();
    i->config = i->dir / "test.toml";
    std::ofstream(i->config) << test_config_text(8);
    i->scans = write_synthetic_inputs(i->dir, 3);
    i->preop_t1 = read_file(i->dir / "preop_t1.nii.gz");
    i->preop_labels = read_file(i->dir / "preop_labels.nii.gz");
  }
  return *g_inputs;
}

// Removes the work folder unless a test failed (then it is kept for a post-mortem).
class CleanUp : public ::testing::Environment {
 public:
  void TearDown() override {
    if (g_inputs && ::testing::UnitTest::GetInstance()->failed_test_count() > 0) g_inputs->tmp.keep();
    g_inputs.reset();
  }
};
const auto* const g_cleanup = ::testing::AddGlobalTestEnvironment(new CleanUp);

DaemonSpec spec(const fs::path& store, const std::string& name, int mpi_ranks = 0) {
  return DaemonSpec{inputs().dir, inputs().config, store, name, mpi_ranks, {}, {}};
}

bool is_scan_event(const Message& m, MessageType type, const std::string& scan_id) {
  if (m.type() != type) return false;
  if (type == MessageType::kEventScanDone) return parse_scan_done_event(m).scan_id == scan_id;
  if (type == MessageType::kEventScanFailed) return parse_scan_failed_event(m).scan_id == scan_id;
  return false;
}

bool progress_at(const Message& m, const std::string& stage, double min_fraction) {
  if (m.type() != MessageType::kEventScanProgress) return false;
  const auto p = parse_scan_progress_event(m);
  return p.stage == stage && p.fraction >= min_fraction;
}

std::string scan_id_of(const Message& push_reply) {
  throw_if_error(push_reply);
  return parse_scan_push_reply(push_reply).scan_id;
}

// Polls scan.list until no scan is queued or processing.
ScanListReply wait_all_finished(Client& c, std::chrono::seconds timeout) {
  const auto until = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    ScanListReply list = c.list();
    bool busy = false;
    for (const auto& s : list.scans) busy |= s.state == ScanState::kQueued || s.state == ScanState::kProcessing;
    if (!busy || std::chrono::steady_clock::now() > until) return list;
    std::this_thread::sleep_for(200ms);
  }
}

std::size_t count_log(const std::string& log, const std::string& needle) {
  std::size_t n = 0;
  for (auto at = log.find(needle); at != std::string::npos; at = log.find(needle, at + 1)) ++n;
  return n;
}

std::vector<fs::path> temporary_leftovers(const fs::path& store) {
  std::vector<fs::path> out;
  for (const auto& e : fs::recursive_directory_iterator(store)) {
    const std::string n = e.path().filename().string();
    if (n.rfind(".tmp-", 0) == 0 || (n.size() > 4 && n.substr(n.size() - 4) == ".tmp")) out.push_back(e.path());
  }
  return out;
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
  int kills = 0, restarts = 0;

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
      const ScanPushReply again = parse_scan_push_reply(c.push(s.labels, s.image, in_flight_client_id));
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
      const std::string id = scan_id_of(c.push(s.labels, s.image, client_id));
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
                    {"result_frames_compared_identical", ledger.results_compared}};
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

// ---------------------------------------------------------------- bad clients

// A TCP connection that starts a ZMTP greeting and a frame header that
// promises a large frame, sends part of it and then stalls.
int stalled_tcp_peer(const std::string& endpoint) {
  const int port = std::stoi(endpoint.substr(endpoint.rfind(':') + 1));
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<std::uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) return -1;
  const unsigned char greeting[] = {0xff, 0, 0, 0, 0, 0, 0, 0, 1, 0x7f, 3, 0};
  [[maybe_unused]] auto n = ::write(fd, greeting, sizeof greeting);
  return fd;
}

TEST(DaemonFaults, VanishingAndNonReadingClientsDoNotBlockOthers) {
  const Inputs& in = inputs();
  Daemon d(spec(in.dir / "store-clients", "clients"));
  Client good(d.endpoint);
  good.load_preop(in.preop_t1, in.preop_labels);
  ASSERT_NO_THROW(good.wait_ready(300s)) << d.log();
  EventRecorder events(d.events);
  const std::string done_scan = scan_id_of(good.push(in.scans[0].labels, in.scans[0].image, "good-0"));
  ASSERT_TRUE(events.wait_for([&](const Message& m) { return is_scan_event(m, MessageType::kEventScanDone, done_scan); }, 300s));
  std::this_thread::sleep_for(2s);  // field.h5/report.png stored
  const std::size_t fds_before = open_fds(d.rank0_pid());
  const std::uint64_t rss_before = resident_kib(d.rank0_pid());

  std::atomic<bool> stop{false};
  int vanished = 0, half_sent = 0, unread_requests = 0;
  zmq::context_t ctx(1);
  std::thread vanishers([&] {
    // Whole pushes sent, socket closed before the reply; and pushes cut off
    // after the first frame (libzmq discards the partial message).
    for (int i = 0; i < 6 && !stop; ++i) {
      zmq::socket_t s(ctx, zmq::socket_type::dealer);
      s.set(zmq::sockopt::linger, i % 2 ? 0 : 2000);
      s.connect(d.endpoint);
      const ScanBytes& scan = in.scans[i % 3];
      ScanPushRequest req{media::nifti_frame("labels", scan.labels), media::nifti_frame("image", scan.image),
                          "gone-" + std::to_string(i)};
      auto wire = encode(make_scan_push_request("gone", req));
      if (i % 2) {
        s.send(zmq::message_t(), zmq::send_flags::sndmore);
        s.send(zmq::buffer(wire[0]), zmq::send_flags::sndmore);
        ++half_sent;
      } else {
        transport::send_request(s, make_scan_push_request("gone", req));
        ++vanished;
      }
      s.close();
      std::this_thread::sleep_for(100ms);
    }
  });
  // Asks for whole results and never reads the replies.
  zmq::socket_t deaf(ctx, zmq::socket_type::dealer);
  deaf.set(zmq::sockopt::linger, 0);
  deaf.set(zmq::sockopt::rcvhwm, 1);
  deaf.set(zmq::sockopt::rcvbuf, 4096);
  deaf.connect(d.endpoint);
  for (int i = 0; i < 40; ++i, ++unread_requests) {
    ScanResultRequest req;
    req.scan_id = done_scan;
    req.parts = all_result_parts();
    transport::send_request(deaf, make_scan_result_request("deaf-" + std::to_string(i), req));
    transport::send_request(deaf, make_status_request("deaf-s-" + std::to_string(i)));
  }
  const int stalled = stalled_tcp_peer(d.endpoint);
  ASSERT_GE(stalled, 0);

  // Meanwhile a well-behaved client is answered every time.
  int answered = 0;
  for (int i = 0; i < 20; ++i) {
    EXPECT_NE(good.status().state, ServerState::kIdle);
    const auto frames = pull_complete(good, done_scan, {ResultPart::kMetrics, ResultPart::kDisplacement});
    EXPECT_EQ(frames.size(), 2u);
    ++answered;
  }
  vanishers.join();
  const std::string fresh = scan_id_of(good.push(in.scans[1].labels, in.scans[1].image, "good-1"));
  ASSERT_TRUE(events.wait_for([&](const Message& m) { return is_scan_event(m, MessageType::kEventScanDone, fresh); }, 300s))
      << d.log();
  // What the vanished clients pushed whole was stored and is processed; the
  // cut-off pushes never arrived. Nothing else appears.
  const ScanListReply list = wait_all_finished(good, 600s);
  std::set<std::string> client_ids;
  for (const auto& s : list.scans) {
    client_ids.insert(s.client_scan_id.value_or(""));
    EXPECT_EQ(s.state, ScanState::kDone) << s.scan_id;
  }
  for (int i = 0; i < 6; i += 2) EXPECT_TRUE(client_ids.count("gone-" + std::to_string(i))) << i;
  for (int i = 1; i < 6; i += 2) EXPECT_FALSE(client_ids.count("gone-" + std::to_string(i))) << i;
  EXPECT_EQ(list.scans.size(), 2u + 3u);

  // Every misbehaving connection closed: the daemon holds no more descriptors
  // than before them (polled: libzmq closes them asynchronously).
  deaf.close();
  ::close(stalled);
  std::size_t fds_after = 0;
  for (int i = 0; i < 100; ++i) {
    fds_after = open_fds(d.rank0_pid());
    if (fds_after <= fds_before) break;
    std::this_thread::sleep_for(100ms);
  }
  EXPECT_LE(fds_after, fds_before);
  // Replies nobody reads are bounded (the ROUTER's send limit), not piled up:
  // 40 unread whole results are ~760 MB; a handful may wait.
  const std::uint64_t rss_after = resident_kib(d.rank0_pid());
  EXPECT_LT(rss_after, rss_before + (256u << 10)) << "replies to a client that never reads piled up";
  std::printf("%s\n", json{{"test", "bad_clients"},
                           {"vanished_after_push", vanished},
                           {"cut_off_mid_message", half_sent},
                           {"unread_requests", 2 * unread_requests},
                           {"stalled_tcp_peers", 1},
                           {"good_client_round_trips", answered},
                           {"fds_before", fds_before},
                           {"fds_after", fds_after},
                           {"rss_kib_before", rss_before},
                           {"rss_kib_after", rss_after}}
                          .dump()
                          .c_str());
  stop = true;
  EXPECT_TRUE(d.process().running());
  d.process().signal(SIGTERM);
  EXPECT_EQ(d.process().wait(60).value_or(-1), 0);
}

// ---------------------------------------------------------------- store refuses writes

struct StoreFault {
  std::string name;
  std::function<void(Daemon&)> refuse_all;      // no write of any size succeeds
  std::function<void(Daemon&)> refuse_results;  // a scan (~100s of KB) fits, a result (MBs) does not
  std::function<void(Daemon&)> restore;         // space returns
};

// The same scenario for each kind of refusal: a refused push is a clear error
// and leaves nothing behind; a result the store refuses is reported and made
// again once space returns; the daemon serves throughout.
// Whether scan_id gets a scan.done after its scan.failed within timeout.
bool done_after_failure(EventRecorder& events, const std::string& scan_id, std::chrono::seconds timeout) {
  const auto until = std::chrono::steady_clock::now() + timeout;
  do {
    bool failed = false;
    for (const Message& m : events.snapshot()) {
      failed = failed || is_scan_event(m, MessageType::kEventScanFailed, scan_id);
      if (failed && is_scan_event(m, MessageType::kEventScanDone, scan_id)) return true;
    }
    std::this_thread::sleep_for(100ms);
  } while (std::chrono::steady_clock::now() < until);
  return false;
}

void refused_writes_scenario(const StoreFault& fault, const fs::path& store) {
  const Inputs& in = inputs();
  Daemon d(spec(store, fault.name));
  Client c(d.endpoint);
  c.load_preop(in.preop_t1, in.preop_labels);
  ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
  EventRecorder events(d.events);
  const std::size_t fds_before = open_fds(d.rank0_pid());
  const ScanBytes &a = in.scans[0], &b = in.scans[1], &cc = in.scans[2];

  fault.refuse_all(d);
  for (int i = 0; i < 3; ++i) {
    const Message reply = c.push(a.labels, a.image, "full-" + std::to_string(i));
    ASSERT_EQ(reply.type(), MessageType::kError);
    const ErrorInfo e = parse_error_reply(reply);
    EXPECT_EQ(e.code, ErrorCode::kInternal);
    EXPECT_NE(e.message.find("NOT stored"), std::string::npos) << e.message;
    std::printf("refused push (%s): %s\n", fault.name.c_str(), e.message.c_str());
  }
  EXPECT_TRUE(c.list().scans.empty()) << "nothing refused is acknowledged or listed";
  EXPECT_TRUE(temporary_leftovers(store).empty());
  EXPECT_EQ(c.status().state, ServerState::kReady);

  fault.refuse_results(d);
  const std::string unstored = scan_id_of(c.push(b.labels, b.image, "fits"));
  const auto failed = events.wait_for(
      [&](const Message& m) { return is_scan_event(m, MessageType::kEventScanFailed, unstored); }, 300s);
  ASSERT_TRUE(failed.has_value()) << d.log();
  const ScanFailedEvent f = parse_scan_failed_event(*failed);
  EXPECT_NE(f.error.message.find("could not be stored"), std::string::npos) << f.error.message;
  EXPECT_TRUE(temporary_leftovers(store).empty()) << "a refused result leaves no partial file";
  const Message pull = c.result(unstored, {ResultPart::kMetrics});
  ASSERT_EQ(pull.type(), MessageType::kError);

  fault.restore(d);
  const std::string after = scan_id_of(c.push(cc.labels, cc.image, "after"));
  ASSERT_TRUE(events.wait_for([&](const Message& m) { return is_scan_event(m, MessageType::kEventScanDone, after); }, 300s))
      << d.log();
  // The refused result had been announced (scan.done comes before the write)
  // and was withdrawn (scan.failed); it is made again after the failure.
  ASSERT_TRUE(done_after_failure(events, unstored, 300s)) << d.log();
  for (const auto& id : {unstored, after})
    EXPECT_EQ(pull_complete(c, id, all_result_parts()).count(frame_name(ResultPart::kDisplacement)), 1u);
  std::size_t fds_after = open_fds(d.rank0_pid());
  EXPECT_LE(fds_after, fds_before) << "failed writes leaked descriptors";
  // And the store reopens as it is.
  d.process().signal(SIGTERM);
  ASSERT_EQ(d.process().wait(60).value_or(-1), 0) << d.log();
  Daemon again(spec(store, fault.name + "-again"));
  Client c2(again.endpoint);
  ASSERT_NO_THROW(c2.wait_ready(300s));
  const ScanListReply list = c2.list();
  ASSERT_EQ(list.scans.size(), 2u);
  for (const auto& s : list.scans) EXPECT_EQ(s.state, ScanState::kDone) << s.scan_id;
  std::printf("%s\n", json{{"test", "store_refuses_writes"}, {"fault", fault.name}, {"pushes_refused", 3},
                           {"results_refused_then_remade", 1}, {"fds_before", fds_before}, {"fds_after", fds_after}}
                          .dump()
                          .c_str());
  again.process().signal(SIGTERM);
  EXPECT_EQ(again.process().wait(60).value_or(-1), 0);
}

void set_file_size_limit(pid_t pid, rlim_t bytes) {
  // Only the soft limit: raising a hard limit again needs CAP_SYS_RESOURCE.
  rlimit limit{};
  ASSERT_EQ(::prlimit(pid, RLIMIT_FSIZE, nullptr, &limit), 0);
  limit.rlim_cur = std::min(bytes, limit.rlim_max);
  ASSERT_EQ(::prlimit(pid, RLIMIT_FSIZE, &limit, nullptr), 0) << "prlimit: " << std::strerror(errno);
}

TEST(DaemonFaults, FileSizeLimitRefusesWritesCleanly) {
  // RLIMIT_FSIZE on the running daemon: every write past the limit fails with
  // EFBIG (SIGXFSZ is ignored by brainshiftd), whatever the user and disk.
  const std::size_t scan_bytes = inputs().scans[1].labels.size() + inputs().scans[1].image.size();
  StoreFault fault{"rlimit-fsize",
                   [](Daemon& d) { set_file_size_limit(d.rank0_pid(), 2048); },
                   [scan_bytes](Daemon& d) { set_file_size_limit(d.rank0_pid(), scan_bytes + (256 << 10)); },
                   [](Daemon& d) { set_file_size_limit(d.rank0_pid(), RLIM_INFINITY); }};
  refused_writes_scenario(fault, inputs().dir / "store-fsize");
}

// Fills the filesystem holding `path` until at most leave_bytes are free
// (0: until a write fails).
void fill(const fs::path& path, std::size_t leave_bytes) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  ASSERT_GE(fd, 0);
  const std::string block(64 << 10, 'f');
  for (std::size_t step : {block.size(), std::size_t{4096}}) {
    while (fs::space(path.parent_path()).available >= leave_bytes + step)
      if (::write(fd, block.data(), step) != static_cast<ssize_t>(step)) break;
  }
  if (leave_bytes == 0)
    while (::write(fd, block.data(), 4096) > 0) {
    }
  ::close(fd);
}

TEST(DaemonFaults, FullFilesystemRefusesWritesCleanly) {
  // A real ENOSPC: the store on a small tmpfs. Needs permission to mount.
  const fs::path mnt = inputs().dir / "small-fs";
  fs::create_directories(mnt);
  if (::mount("tmpfs", mnt.c_str(), "tmpfs", 0, "size=96m") != 0)
    GTEST_SKIP() << "cannot mount a tmpfs here (" << std::strerror(errno) << "); the RLIMIT_FSIZE test covers refusals";
  struct Unmount {
    fs::path at;
    ~Unmount() { ::umount2(at.c_str(), MNT_DETACH); }
  } unmount{mnt};
  const std::size_t scan_bytes = inputs().scans[1].labels.size() + inputs().scans[1].image.size();
  const fs::path filler = mnt / "filler";
  StoreFault fault{"tmpfs-full",
                   [filler](Daemon&) { fill(filler, 0); },
                   [filler, scan_bytes](Daemon&) {
                     fs::remove(filler);
                     fill(filler, scan_bytes + (512 << 10));
                   },
                   [filler](Daemon&) { fs::remove(filler); }};
  refused_writes_scenario(fault, mnt / "store");
}

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
