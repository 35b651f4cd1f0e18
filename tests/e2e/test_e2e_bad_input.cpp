// Bad input through a running brainshiftd over real sockets (PROTOCOL.md
// sections 3, 7, 9) and through `brainshift register`: a battery of malformed
// messages and broken images. Each gets its typed error (or, for an image that
// only the pipeline can judge, a failed scan with a code and a message naming
// the problem); the daemon keeps serving (a status after every input); the
// result stored before the battery is byte-identical after it, and no refused
// scan is stored.
#include <gtest/gtest.h>

#include <signal.h>

#include <chrono>
#include <cstring>
#include <limits>
#include <fstream>
#include <thread>
#include <tuple>

#include <nlohmann/json.hpp>
#include <zmq.hpp>

#include "bad_images.h"
#include "client/exit_codes.h"
#include "image/nifti_io.h"
#include "process.h"
#include "temp_dir.h"
#include "protocol/media.h"
#include "protocol/requests.h"
#include "protocol/transport.h"
#include "synthetic_case.h"

using namespace brainshift;
using namespace brainshift::e2e;
namespace fs = std::filesystem;
namespace bp = brainshift::protocol;
namespace tp = brainshift::protocol::transport;
using bp::ErrorCode;
using nlohmann::json;
using namespace std::chrono_literals;

namespace cli = brainshift::cli;

namespace {

constexpr std::size_t kMaxFrameBytes = std::size_t{1} << 20;  // configured below; hard cap 2 MiB

struct Env {
  test::TempDir tmp{"bad-input"};
  fs::path dir = tmp.path(), config, store;
  std::unique_ptr<Process> daemon;
  std::string endpoint;
};
Env* g = nullptr;

fs::path path(const std::string& name) { return g->dir / name; }

std::string config_text() {
  // Unauthenticated shutdown allowed (loopback, no CURVE) so that a shutdown
  // with a bad field reaches its parser; the test never sends a valid one.
  return "[server]\npreop = \"none\"\nqueue_depth = 3\nmax_frame_bytes = " + std::to_string(kMaxFrameBytes) +
         "\n\n[security]\nallow_unauthenticated_shutdown = true\n"
         "\n[mesh]\ncell_size_mm = 7.0\nfacet_size_mm = 4.0\nfacet_distance_mm = 1.5\n";
}

RunResult client(std::vector<std::string> args, double timeout_s = 300) {
  std::vector<std::string> argv = {BRAINSHIFT_BIN, "--server", g->endpoint, "--timeout", "20"};
  argv.insert(argv.end(), args.begin(), args.end());
  return run(argv, g->dir, timeout_s);
}

std::string daemon_log() { return read_file(path("daemon.err")); }

// A DEALER of our own: sends exactly the frames given (after the delimiter).
class RawClient {
 public:
  RawClient() : socket_(context_, zmq::socket_type::dealer) {
    socket_.set(zmq::sockopt::linger, 0);
    socket_.connect(g->endpoint);
  }
  void send_frames(const tp::Wire& frames, bool with_delimiter = true) {
    tp::Wire wire = frames;
    if (with_delimiter) wire.insert(wire.begin(), "");
    tp::send_wire(socket_, wire);
  }
  std::optional<bp::Message> reply(std::chrono::milliseconds timeout = 20s) {
    return tp::receive_reply(socket_, bp::Limits::client_inbound(), timeout);
  }
  // Sends the frames and returns the error reply's code and message.
  bp::ErrorInfo error_for(const tp::Wire& frames, const std::string& expected_id) {
    send_frames(frames);
    const auto r = reply();
    if (!r) throw std::runtime_error("no reply: " + daemon_log());
    EXPECT_EQ(r->request_id(), expected_id);
    return bp::parse_error_reply(*r);
  }
  bp::Message request(const bp::Message& m) {
    tp::send_request(socket_, m);
    auto r = reply(60s);
    if (!r) throw std::runtime_error("no reply to " + m.request_id() + ": " + daemon_log());
    return *r;
  }

 private:
  zmq::context_t context_;
  zmq::socket_t socket_;
};

// The daemon answers a status request: it is alive and not wedged.
void expect_serving(const std::string& after) {
  RawClient c;
  const bp::Message r = c.request(bp::make_status_request("alive"));
  EXPECT_EQ(r.type(), bp::MessageType::kStatusReply) << "after " << after;
  EXPECT_TRUE(g->daemon->running()) << "the daemon died after " << after << ": " << daemon_log();
}

bp::ScanListReply scan_list() {
  RawClient c;
  return bp::parse_scan_list_reply(c.request(bp::make_scan_list_request("list", {1000})));
}

// Waits until no scan is queued or processing.
bp::ScanListReply wait_idle() {
  const auto until = std::chrono::steady_clock::now() + 120s;
  while (std::chrono::steady_clock::now() < until) {
    const auto list = scan_list();
    const bool busy = std::any_of(list.scans.begin(), list.scans.end(), [](const bp::ScanSummary& s) {
      return s.state == bp::ScanState::kQueued || s.state == bp::ScanState::kProcessing;
    });
    if (!busy) return list;
    std::this_thread::sleep_for(100ms);
  }
  throw std::runtime_error("scans still running: " + daemon_log());
}

std::string header(const json& h) { return h.dump(); }

json push_header(const std::string& id, std::vector<std::pair<std::string, std::size_t>> frames,
                 const std::string& media = std::string(bp::media::kNiftiGz)) {
  json h = {{"v", 1}, {"type", "scan.push"}, {"request_id", id}};
  h["frames"] = json::array();
  for (const auto& [name, size] : frames) h["frames"].push_back({{"name", name}, {"media_type", media}, {"size", size}});
  return h;
}

// Peak resident memory of a process (VmHWM, kB).
long peak_rss_kb(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(in, line);)
    if (line.rfind("VmHWM:", 0) == 0) return std::stol(line.substr(6));
  return -1;
}

class BadInputE2E : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    g = new Env;
    g->config = g->dir / "test.toml";
    g->store = g->dir / "store";
    std::ofstream(g->config) << config_text();
    write_synthetic_preop(g->dir);
    write_synthetic_scan(g->dir, "scan_a", {4.0, -3.0, 2.5});
    const fs::path ready = g->dir / "daemon.ready";
    g->daemon = std::make_unique<Process>(
        std::vector<std::string>{BRAINSHIFTD_BIN, "--config", g->config.string(), "--store", g->store.string(),
                                 "--endpoint", "tcp://127.0.0.1:*", "--events", "tcp://127.0.0.1:*", "--ready-file",
                                 ready.string()},
        g->dir / "daemon.out", g->dir / "daemon.err");
    const auto until = std::chrono::steady_clock::now() + 60s;
    while (!fs::exists(ready) && std::chrono::steady_clock::now() < until && g->daemon->running())
      std::this_thread::sleep_for(50ms);
    ASSERT_TRUE(fs::exists(ready)) << daemon_log();
    g->endpoint = json::parse(read_file(ready)).at("endpoint").get<std::string>();

    const RunResult load = client({"load-preop", "--image", path("preop_t1.nii.gz").string(), "--labels",
                                   path("preop_labels.nii.gz").string(), "--wait"});
    ASSERT_EQ(load.code, 0) << load.err << daemon_log();
    const RunResult a = client({"push", "--labels", path("scan_a_labels.nii.gz").string(), "--image",
                                path("scan_a_t1.nii.gz").string(), "--id", "good-a", "--wait"});
    ASSERT_EQ(a.code, 0) << a.err << daemon_log();
    good_scan_ = a.out.substr(0, a.out.find('\n'));
    // Deferred parts (field.h5, report.png, metrics) follow event.scan.done:
    // wait until none is pending, so the reference is the whole result.
    const auto whole_by = std::chrono::steady_clock::now() + 60s;
    bool pending = true;
    while (pending && std::chrono::steady_clock::now() < whole_by) {
      const bp::ScanResultReply reply = pull_reply();
      pending = std::any_of(reply.unavailable.begin(), reply.unavailable.end(),
                            [](const bp::UnavailablePart& u) { return u.pending; });
      if (pending) std::this_thread::sleep_for(100ms);
    }
    ASSERT_FALSE(pending) << daemon_log();
    good_result_ = pull_everything();
    ASSERT_TRUE(good_result_.count("displacement_itk") && good_result_.count("report") && good_result_.count("metrics"))
        << daemon_log();
  }
  static void TearDownTestSuite() {
    if (g->daemon && g->daemon->running()) {
      g->daemon->signal(SIGTERM);
      EXPECT_EQ(g->daemon->wait(30).value_or(-1), 0) << "the daemon did not stop cleanly: " << daemon_log();
    }
    g->daemon.reset();  // SIGKILL if it is somehow still running
    if (::testing::UnitTest::GetInstance()->failed_test_count() > 0) g->tmp.keep();
    delete g;
  }

  // Every part of the good scan: the reply (frames = the bytes the store holds).
  static bp::ScanResultReply pull_reply() {
    RawClient c;
    const bp::Message r = c.request(bp::make_scan_result_request(
        "pull", {good_scan_,
                 {bp::ResultPart::kDisplacement, bp::ResultPart::kDisplacementItk, bp::ResultPart::kWarpedImage,
                  bp::ResultPart::kWarpedLabels, bp::ResultPart::kModels, bp::ResultPart::kMetrics,
                  bp::ResultPart::kTimings, bp::ResultPart::kReport},
                 {}}));
    return bp::parse_scan_result_reply(r);
  }
  static std::map<std::string, std::string> pull_everything() {
    std::map<std::string, std::string> parts;
    for (const auto& f : pull_reply().frames) parts[f.name] = f.bytes;
    return parts;
  }

  static void expect_good_result_unchanged(const std::string& after) {
    const auto now = pull_everything();
    ASSERT_EQ(now.size(), good_result_.size()) << after;
    for (const auto& [name, bytes] : good_result_) {
      ASSERT_TRUE(now.count(name)) << name << " vanished after " << after;
      EXPECT_TRUE(now.at(name) == bytes) << name << " changed after " << after;
    }
  }

  static std::string good_scan_;
  static std::map<std::string, std::string> good_result_;
};
std::string BadInputE2E::good_scan_;
std::map<std::string, std::string> BadInputE2E::good_result_;

TEST_F(BadInputE2E, ProtocolBatteryGetsTypedErrorsAndTheDaemonKeepsServing) {
  const std::size_t scans_before = scan_list().scans.size();
  const std::string labels = read_file(path("scan_a_labels.nii.gz"));
  const std::string image = read_file(path("scan_a_t1.nii.gz"));
  const std::size_t n_labels = labels.size();
  ASSERT_LT(n_labels + image.size(), kMaxFrameBytes) << "the synthetic scan must fit the configured limit";
  struct Case {
    std::string what;
    tp::Wire frames;
    std::string id;  // expected request_id of the error reply
    ErrorCode code;
  };
  const json status = {{"v", 1}, {"type", "status"}, {"request_id", "b"}};
  auto with = [&](json h, const std::string& key, json value) {
    if (value.is_null()) h.erase(key);
    else h[key] = std::move(value);
    return h;
  };
  const std::string deep = std::string(20000, '[') + std::string(20000, ']');
  const std::string bad_table = R"({"v":1,"structures":{"brain":[0,70000]}})";
  const std::vector<Case> cases = {
      {"wrong version", {header(with(status, "v", 2))}, "b", ErrorCode::kVersionMismatch},
      {"version as a string", {header(with(status, "v", "1"))}, "b", ErrorCode::kVersionMismatch},
      {"missing version", {header(with(status, "v", nullptr))}, "b", ErrorCode::kVersionMismatch},
      {"unknown message type", {header(with(status, "type", "scan.delete"))}, "b", ErrorCode::kUnknownType},
      {"a reply type sent as a request", {header(with(status, "type", "status.reply"))}, "b", ErrorCode::kUnknownType},
      {"missing type", {header(with(status, "type", nullptr))}, "b", ErrorCode::kBadHeader},
      {"malformed JSON", {R"({"v":1,"type":"status","request_id":)"}, "", ErrorCode::kMalformedJson},
      {"JSON that is not an object", {"[1,2,3]"}, "", ErrorCode::kMalformedJson},
      {"header that is not UTF-8", {"{\"v\":1,\"type\":\"status\",\"request_id\":\"\xff\xfe\"}"}, "",
       ErrorCode::kMalformedJson},
      {"empty header frame", {""}, "", ErrorCode::kMalformedJson},
      {"request_id with a space", {header(with(status, "request_id", "a b"))}, "", ErrorCode::kBadHeader},
      {"missing request_id", {header(with(status, "request_id", nullptr))}, "", ErrorCode::kBadHeader},
      {"header nested 20000 levels deep", {R"({"v":1,"type":"status","request_id":"b","x":)" + deep + "}"}, "",
       ErrorCode::kTooLarge},
      {"header over 64 KiB", {header(with(status, "pad", std::string(70000, 'x')))}, "", ErrorCode::kTooLarge},
      {"missing frame (declared, not sent)", {header(push_header("b", {{"labels", n_labels}}))}, "b",
       ErrorCode::kFrameCountMismatch},
      {"extra frame (sent, not declared)", {header(push_header("b", {{"labels", n_labels}})), labels, image}, "b",
       ErrorCode::kFrameCountMismatch},
      {"header claims more data than was sent", {header(push_header("b", {{"labels", n_labels + 1000}})), labels},
       "b", ErrorCode::kFrameSizeMismatch},
      {"header claims 2^64-1 bytes",
       {R"({"v":1,"type":"scan.push","request_id":"b","frames":[{"name":"labels","media_type":"application/x-nifti-1+gzip","size":18446744073709551615}]})",
        labels},
       "b", ErrorCode::kFrameSizeMismatch},
      {"negative frame size", {header(with(push_header("b", {}), "frames", json::array({{{"name", "labels"}, {"media_type", "application/x-nifti-1+gzip"}, {"size", -5}}})))},
       "b", ErrorCode::kBadHeader},
      {"frame over the configured size limit",
       {header(push_header("b", {{"labels", kMaxFrameBytes + 4096}})), labels + std::string(kMaxFrameBytes + 4096 - n_labels, '\0')},
       "b", ErrorCode::kTooLarge},
      {"33 frames", [&] {
         tp::Wire w{header(status)};
         for (int i = 0; i < 33; ++i) w.push_back("x");
         return w;
       }(),
       "b", ErrorCode::kTooLarge},
      {"undeclared frame name", {header(push_header("b", {{"labels", n_labels}, {"extra", 2}})), labels, "{}"}, "b",
       ErrorCode::kInvalidRequest},
      // An image alone is a scan (revision 4); neither labels nor image is not.
      {"scan.push with neither labels nor image", {header(push_header("b", {}))}, "b", ErrorCode::kInvalidRequest},
      {"labels frame that is not gzip", {header(push_header("b", {{"labels", 9}})), "not gzip!"}, "b",
       ErrorCode::kInvalidRequest},
      {"unknown media type", {header(push_header("b", {{"labels", n_labels}}, "image/jpeg")), labels}, "b",
       ErrorCode::kInvalidRequest},
      {"duplicate frame names", {header(push_header("b", {{"labels", n_labels}, {"labels", n_labels}})), labels, labels},
       "b", ErrorCode::kBadHeader},
      {"client_scan_id with a space", {header(with(push_header("b", {{"labels", n_labels}}), "client_scan_id", "a b")), labels},
       "b", ErrorCode::kInvalidRequest},
      {"status with a frame", {header(with(status, "frames", json::array({{{"name", "x"}, {"media_type", "application/json"}, {"size", 2}}}))), "{}"},
       "b", ErrorCode::kInvalidRequest},
      {"preop.load with the atlas and frames",
       {header(json{{"v", 1}, {"type", "preop.load"}, {"request_id", "b"}, {"use_default_atlas", true},
                    {"frames", json::array({{{"name", "t1"}, {"media_type", "application/x-nifti-1+gzip"}, {"size", n_labels}}})}}),
        labels},
       "b", ErrorCode::kInvalidRequest},
      {"preop.load without frames", {header(json{{"v", 1}, {"type", "preop.load"}, {"request_id", "b"}})}, "b",
       ErrorCode::kInvalidRequest},
      {"label table out of range",
       {header(json{{"v", 1}, {"type", "preop.load"}, {"request_id", "b"},
                    {"frames", json::array({{{"name", "t1"}, {"media_type", "application/x-nifti-1+gzip"}, {"size", image.size()}},
                                            {{"name", "labels"}, {"media_type", "application/x-nifti-1+gzip"}, {"size", n_labels}},
                                            {{"name", "label_table"}, {"media_type", "application/json"}, {"size", bad_table.size()}}})}}),
        image, labels, bad_table},
       "b", ErrorCode::kInvalidRequest},
      {"scan.result of an unknown scan",
       {header(json{{"v", 1}, {"type", "scan.result"}, {"request_id", "b"}, {"scan_id", "scan-424242"}, {"parts", {"metrics"}}})},
       "b", ErrorCode::kNotFound},
      {"scan.result with an unknown part",
       {header(json{{"v", 1}, {"type", "scan.result"}, {"request_id", "b"}, {"scan_id", good_scan_}, {"parts", {"bogus"}}})},
       "b", ErrorCode::kInvalidRequest},
      {"scan.result with no parts",
       {header(json{{"v", 1}, {"type", "scan.result"}, {"request_id", "b"}, {"scan_id", good_scan_}, {"parts", json::array()}})},
       "b", ErrorCode::kInvalidRequest},
      {"scan.list limit 0", {header(json{{"v", 1}, {"type", "scan.list"}, {"request_id", "b"}, {"limit", 0}})}, "b",
       ErrorCode::kInvalidRequest},
      {"scan.list limit not a number", {header(json{{"v", 1}, {"type", "scan.list"}, {"request_id", "b"}, {"limit", "all"}})},
       "b", ErrorCode::kInvalidRequest},
      {"shutdown reason not a string", {header(json{{"v", 1}, {"type", "shutdown"}, {"request_id", "b"}, {"reason", 5}})},
       "b", ErrorCode::kInvalidRequest},
  };
  RawClient c;
  for (const auto& k : cases) {
    const bp::ErrorInfo e = c.error_for(k.frames, k.id);
    EXPECT_EQ(e.code, k.code) << k.what << ": got " << bp::to_string(e.code) << " (" << e.message << ")";
    EXPECT_FALSE(e.message.empty()) << k.what;
    expect_serving(k.what);
  }
  std::printf("protocol battery: %zu bad messages, each a typed error\n", cases.size());

  // Messages that cannot be answered (no envelope delimiter, or nothing after
  // it) are dropped and logged; the daemon goes on.
  RawClient unanswerable;
  unanswerable.send_frames({}, true);
  EXPECT_FALSE(unanswerable.reply(500ms).has_value());
  unanswerable.send_frames({header(status)}, false);
  EXPECT_FALSE(unanswerable.reply(500ms).has_value());
  expect_serving("unanswerable messages");
  // A frame over the hard cap (2 x 1 MiB): libzmq drops the connection before
  // allocating it, no reply; other clients are unaffected.
  RawClient greedy;
  greedy.send_frames({header(push_header("b", {{"labels", 3 * kMaxFrameBytes}})), std::string(3 * kMaxFrameBytes, '\0')});
  EXPECT_FALSE(greedy.reply(1s).has_value());
  expect_serving("a frame over the hard cap");

  EXPECT_EQ(scan_list().scans.size(), scans_before) << "a refused request stored a scan";
  expect_good_result_unchanged("the protocol battery");
}

TEST_F(BadInputE2E, BrokenImagesThroughScanPushAreTypedErrorsOrFailedScans) {
  const std::size_t scans_before = scan_list().scans.size();
  const auto cases = image_cases(g->dir);
  RawClient c;
  std::size_t refused = 0, failed = 0;
  for (std::size_t n = 0; n < cases.size(); ++n) {
    const ImageCase& k = cases[n];
    bp::ScanPushRequest push{bp::media::nifti_frame("labels", k.labels), std::nullopt, "bad-" + std::to_string(n)};
    if (k.image) push.image = bp::media::nifti_frame("image", *k.image);
    const long rss_before = peak_rss_kb(g->daemon->pid());
    const bp::Message reply = c.request(bp::make_scan_push_request("img-" + std::to_string(n), push));
    if (k.refused_at_push) {
      ASSERT_EQ(reply.type(), bp::MessageType::kError) << k.what << " was accepted";
      const bp::ErrorInfo e = bp::parse_error_reply(reply);
      EXPECT_EQ(e.code, ErrorCode::kInvalidRequest) << k.what << ": " << e.message;
      EXPECT_NE(e.message.find(k.fragment), std::string::npos) << k.what << ": " << e.message;
      ++refused;
    } else {
      // Only the pipeline can judge it: stored, then failed with a code and a reason.
      const bp::ScanPushReply ok = bp::parse_scan_push_reply(reply);
      wait_idle();
      const bp::Message result = c.request(bp::make_scan_result_request("r-" + std::to_string(n), {ok.scan_id, {bp::ResultPart::kMetrics}, {}}));
      const bp::ErrorInfo e = bp::parse_error_reply(result);
      EXPECT_EQ(e.code, ErrorCode::kScanFailed) << k.what;
      EXPECT_NE(e.message.find(k.fragment), std::string::npos) << k.what << ": " << e.message;
      const auto list = scan_list();
      const auto it = std::find_if(list.scans.begin(), list.scans.end(),
                                   [&](const bp::ScanSummary& s) { return s.scan_id == ok.scan_id; });
      ASSERT_NE(it, list.scans.end());
      EXPECT_EQ(it->state, bp::ScanState::kFailed) << k.what;
      ASSERT_TRUE(it->error.has_value()) << k.what;
      EXPECT_EQ(it->error->code, ErrorCode::kInvalidRequest) << k.what << ": " << it->error->message;
      ++failed;
    }
    if (k.what == "gzip bomb") {
      // Refused from the header: the daemon's peak memory did not grow by the claim.
      const long growth_mb = (peak_rss_kb(g->daemon->pid()) - rss_before) / 1024;
      std::printf("gzip bomb (4 GiB claimed, %zu bytes sent): peak RSS grew by %ld MiB\n", k.labels.size(), growth_mb);
      EXPECT_LT(growth_mb, 256);
    }
    expect_serving(k.what);
  }
  std::printf("image battery through scan.push: %zu refused at push, %zu failed scans\n", refused, failed);
  EXPECT_EQ(scan_list().scans.size(), scans_before + failed) << "a scan refused at push was stored";
  expect_good_result_unchanged("the image battery");
  // And the warm state still registers a good scan (same bytes, new id).
  const RunResult again = client({"push", "--labels", path("scan_a_labels.nii.gz").string(), "--id", "good-again", "--wait"});
  EXPECT_EQ(again.code, 0) << again.err << daemon_log();
}

TEST_F(BadInputE2E, BrokenImagesThroughRegisterExitWithAClearError) {
  const auto cases = image_cases(g->dir);
  for (std::size_t n = 0; n < cases.size(); ++n) {
    const ImageCase& k = cases[n];
    const fs::path labels = path("register_bad_" + std::to_string(n) + "_labels.nii.gz");
    std::ofstream(labels, std::ios::binary) << k.labels;
    std::vector<std::string> argv = {BRAINSHIFT_BIN, "register", "--config", g->config.string(), "--preop-image",
                                     path("preop_t1.nii.gz").string(), "--preop-labels",
                                     path("preop_labels.nii.gz").string(), "--intraop-labels", labels.string(),
                                     "--out", path("register_bad_" + std::to_string(n)).string()};
    if (k.image) {
      const fs::path image = path("register_bad_" + std::to_string(n) + "_t1.nii.gz");
      std::ofstream(image, std::ios::binary) << *k.image;
      argv.insert(argv.end(), {"--intraop-image", image.string()});
    }
    const RunResult r = run(argv, g->dir, 600);
    EXPECT_EQ(r.code, cli::kExitError) << k.what << ": " << r.err;
    EXPECT_NE(r.err.find("error: "), std::string::npos) << k.what << ": " << r.err;
    EXPECT_NE(r.err.find(k.fragment), std::string::npos) << k.what << ": " << r.err;
    EXPECT_FALSE(fs::exists(path("register_bad_" + std::to_string(n)))) << k.what << ": outputs written";
    std::printf("register, %s: exit %d in %.1f s\n", k.what.c_str(), r.code, r.seconds);
  }
}

TEST_F(BadInputE2E, ARefusedNonRigidResultIsExit4AndMarkedAffineOnlyInMetrics) {
  // A surface gate no match can pass: `brainshift register` must say so by its
  // exit code and in metrics.json, and still write the (affine-only) outputs.
  const fs::path config = path("strict_gates.toml");
  std::ofstream(config) << config_text() << "\n[gates]\nmax_mean_surface_residual_mm = 0.000001\n";
  const fs::path out = path("register_fallback");
  const RunResult r = run({BRAINSHIFT_BIN, "register", "--config", config.string(), "--preop-image",
                           path("preop_t1.nii.gz").string(), "--preop-labels", path("preop_labels.nii.gz").string(),
                           "--intraop-labels", path("scan_a_labels.nii.gz").string(), "--out", out.string()},
                          g->dir, 600);
  EXPECT_EQ(r.code, cli::kExitFallback) << r.err;
  EXPECT_NE(r.err.find("AFFINE-ONLY"), std::string::npos) << r.err;
  const json metrics = json::parse(read_file(out / "metrics.json"));
  EXPECT_EQ(metrics.at("result"), "affine_only_fallback");
  EXPECT_NE(metrics.at("fallback_reason").get<std::string>().find("diverged"), std::string::npos);
  EXPECT_TRUE(fs::exists(out / "field.nii.gz"));
}

TEST_F(BadInputE2E, BrokenPreopUploadsLeaveTheWarmPreopInPlace) {
  RawClient c;
  const std::string preop_id = *bp::parse_status_reply(c.request(bp::make_status_request("s"))).preop_id;
  const std::string t1 = read_file(path("preop_t1.nii.gz"));
  const LabelImage labels = read_label_image(path("preop_labels.nii.gz"));
  auto upload = [&](const std::string& t1_bytes, const LabelImage& l) {
    return c.request(bp::make_preop_load_request(
        "p", {false, bp::media::nifti_frame("t1", t1_bytes), bp::media::nifti_frame("labels", label_image_to_bytes(l, true)), {}}));
  };
  LabelImage moved = labels;
  // Half a voxel: not the T1's grid, nor a part of it shifted by whole voxels.
  moved.grid.world_from_voxel.col(3) += 0.5 * moved.grid.world_from_voxel.col(1);
  LabelImage empty = labels;
  std::fill(empty.voxels.begin(), empty.voxels.end(), 0);
  LabelImage unknown = labels;
  unknown.voxels[unknown.voxels.size() / 2] = 9;
  const std::vector<std::tuple<std::string, bp::Message, std::string>> refused = {
      {"truncated t1", upload(t1.substr(0, t1.size() / 2), labels), "truncated"},
      {"labels on another grid", upload(t1, moved), "grid differs"},
      {"no brain label", upload(t1, empty), "no brain"},
      {"a label outside the default table", upload(t1, unknown), "not a value of the daemon's label table"},
  };
  for (const auto& [what, reply, fragment] : refused) {
    ASSERT_EQ(reply.type(), bp::MessageType::kError) << what << " was accepted";
    const bp::ErrorInfo e = bp::parse_error_reply(reply);
    EXPECT_EQ(e.code, ErrorCode::kInvalidRequest) << what << ": " << e.message;
    EXPECT_NE(e.message.find(fragment), std::string::npos) << what << ": " << e.message;
  }
  // Accepted at the request, refused by the warm-up: a brain of 8 voxels.
  LabelImage speck = labels;
  std::fill(speck.voxels.begin(), speck.voxels.end(), 0);
  for (int k = 30; k < 32; ++k)
    for (int j = 40; j < 42; ++j)
      for (int i = 35; i < 37; ++i) speck.at(i, j, k) = 1;
  const bp::Message accepted = upload(t1, speck);
  ASSERT_EQ(accepted.type(), bp::MessageType::kPreopLoadReply) << bp::parse_error_reply(accepted).message;
  bp::StatusReply status;
  const auto until = std::chrono::steady_clock::now() + 120s;
  do {
    std::this_thread::sleep_for(100ms);
    status = bp::parse_status_reply(c.request(bp::make_status_request("s")));
  } while (status.state == bp::ServerState::kLoadingPreop && std::chrono::steady_clock::now() < until);
  ASSERT_TRUE(status.last_error.has_value()) << "a preop of 8 voxels warmed up: " << daemon_log();
  // Bad input, not a server fault (it used to surface as "internal" from the solver set-up).
  EXPECT_EQ(status.last_error->code, ErrorCode::kInvalidRequest) << status.last_error->message;
  EXPECT_NE(status.last_error->message.find("too small to mesh"), std::string::npos) << status.last_error->message;
  // Refused: the warm preop was never replaced.
  status = bp::parse_status_reply(c.request(bp::make_status_request("s")));
  EXPECT_EQ(status.state, bp::ServerState::kReady);
  EXPECT_EQ(status.preop_id, preop_id);
  // The daemon still registers against it, to the same field as before.
  const bp::Message pushed = c.request(bp::make_scan_push_request(
      "again", {bp::media::nifti_frame("labels", read_file(path("scan_a_labels.nii.gz"))),
                bp::media::nifti_frame("image", read_file(path("scan_a_t1.nii.gz"))), std::string("same-as-a")}));
  const std::string scan = bp::parse_scan_push_reply(pushed).scan_id;
  wait_idle();
  const bp::ScanResultReply r = bp::parse_scan_result_reply(
      c.request(bp::make_scan_result_request("f", {scan, {bp::ResultPart::kDisplacement}, {}})));
  ASSERT_NE(r.find("displacement"), nullptr);
  const VectorImage3 now = vector_image_from_bytes(r.find("displacement")->bytes, "now", std::size_t{1} << 30);
  const VectorImage3 before = vector_image_from_bytes(good_result_.at("displacement"), "before", std::size_t{1} << 30);
  ASSERT_EQ(now.vectors.size(), before.vectors.size());
  float worst = 0;
  for (std::size_t i = 0; i < now.vectors.size(); ++i)
    worst = std::max(worst, (now.vectors[i] - before.vectors[i]).cwiseAbs().maxCoeff());
  EXPECT_LT(worst, 1e-4f) << "the warm state changed";
  expect_good_result_unchanged("the broken preop uploads");
}

}  // namespace
