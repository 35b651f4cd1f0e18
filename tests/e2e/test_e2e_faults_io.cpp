// brainshiftd under faults of its sockets and files, with real processes:
// clients that vanish, never read or stall mid-frame, and a store that
// refuses writes (a file-size limit on the daemon; a full tmpfs when mounting
// is permitted). Counts are printed as JSON for docs/reliability/faults.md.
#include <gtest/gtest.h>

#include <netinet/in.h>
#include <signal.h>
#include <sys/mount.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <functional>
#include <set>
#include <thread>

#include <nlohmann/json.hpp>

#include "fault_fixture.h"
#include "protocol/media.h"
#include "protocol/transport.h"

namespace brainshift::e2e {
namespace {

using namespace protocol;
using namespace std::chrono_literals;

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

}  // namespace
}  // namespace brainshift::e2e
