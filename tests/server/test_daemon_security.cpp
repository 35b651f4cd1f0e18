// brainshiftd's socket side with CURVE on: run_daemon (the real sockets, ZAP
// handler and request loop) over tcp loopback with the engine double, and
// clients holding scanner, viewer, admin, unknown or no keys. Checks the role
// table of PROTOCOL.md section 13 end to end and that strangers get nothing
// while the others keep being served.
#include <gtest/gtest.h>

#include <fstream>
#include <thread>

#include <nlohmann/json.hpp>
#include <spdlog/sinks/ringbuffer_sink.h>
#include <spdlog/spdlog.h>

#include "image/nifti_io.h"
#include "protocol/curve_keys.h"
#include "protocol/events.h"
#include "protocol/media.h"
#include "protocol/requests.h"
#include "protocol/transport.h"
#include "server/curve_auth.h"
#include "server/daemon.h"
#include "test_support.h"

using namespace brainshift;
using namespace brainshift::server;
using namespace brainshift::protocol;
using namespace std::chrono_literals;
namespace curve = brainshift::protocol::curve;
namespace tp = brainshift::protocol::transport;
namespace fs = std::filesystem;

namespace {

struct Keys {
  curve::KeyPair server, scanner, viewer, admin, stranger;
};

// The daemon in a thread; stopped by the admin's shutdown or, failing that, by `stop`.
class CurveDaemon {
 public:
  CurveDaemon() {
    const fs::path keys = dir_.path() / "keys";
    fs::create_directories(keys);
    keys_.server = curve::write_new_key_pair((keys / "server").string());
    for (auto* k : {&keys_.scanner, &keys_.viewer, &keys_.admin, &keys_.stranger}) *k = curve::generate_key_pair();
    DaemonOptions o;
    o.settings.endpoint = "tcp://127.0.0.1:*";
    o.settings.events = "tcp://127.0.0.1:*";
    o.settings.store = dir_.path() / "store";
    o.settings.preop.kind = DefaultPreop::Kind::none;
    o.settings.security.curve = true;
    o.settings.security.server_secret_key_file = curve::secret_key_path((keys / "server").string());
    o.settings.security.clients = {{"or1-scanner", Role::scanner, keys_.scanner.public_z85},
                                   {"viewer-station", Role::viewer, keys_.viewer.public_z85},
                                   {"it-admin", Role::admin, keys_.admin.public_z85}};
    validate_endpoints(o.settings);
    o.ready_file = dir_.path() / "ready.json";
    daemon_ = std::make_unique<test::DaemonThread>(o, engine_);
  }
  int join() { return daemon_->join(); }

  std::unique_ptr<zmq::socket_t> socket(zmq::socket_type type, const curve::KeyPair* own) {
    auto s = std::make_unique<zmq::socket_t>(ctx_, type);
    s->set(zmq::sockopt::linger, 0);
    if (own) curve::set_client_options(*s, {keys_.server.public_z85, *own});
    return s;
  }
  // One request; nullopt when no reply came within `wait`.
  std::optional<Message> call(const curve::KeyPair* own, const Message& request,
                              std::chrono::milliseconds wait = 10s) {
    auto s = socket(zmq::socket_type::dealer, own);
    s->connect(endpoint());
    tp::send_request(*s, request);
    return tp::receive_reply(*s, Limits::client_inbound(), wait);
  }
  ErrorCode error_of(const curve::KeyPair* own, const Message& request) {
    const auto reply = call(own, request);
    if (!reply) throw std::runtime_error("no reply");
    if (reply->type() != MessageType::kError) return ErrorCode::kInternal;  // "not an error" for the checks below
    return parse_error_reply(*reply).code;
  }
  MessageType type_of(const curve::KeyPair* own, const Message& request) {
    const auto reply = call(own, request);
    if (!reply) throw std::runtime_error("no reply");
    return reply->type();
  }

  const Keys& keys() const { return keys_; }
  const std::string& endpoint() const { return daemon_->endpoint(); }
  const std::string& events() const { return daemon_->events(); }

 private:
  test::TempDir dir_;
  Keys keys_;
  test::FakeEngine engine_;
  zmq::context_t ctx_{1};
  std::unique_ptr<test::DaemonThread> daemon_;
};

Message push_request(const std::string& rid) {
  ScanPushRequest r;
  r.labels = media::nifti_frame("labels", label_image_to_bytes(test::ball_labels(12), true));
  return make_scan_push_request(rid, r);
}

Message atlas_request(const std::string& rid) {
  PreopLoadRequest r;
  r.use_default_atlas = true;
  return make_preop_load_request(rid, r);
}

TEST(DaemonSecurity, RolesStrangersAndEventsOverCurve) {
  CurveDaemon d;
  const Keys& k = d.keys();

  // Events: an allowed subscriber (the viewer) and a stranger, both before anything happens.
  auto viewer_sub = d.socket(zmq::socket_type::sub, &k.viewer);
  auto stranger_sub = d.socket(zmq::socket_type::sub, &k.stranger);
  for (auto* s : {viewer_sub.get(), stranger_sub.get()}) {
    s->set(zmq::sockopt::subscribe, "event.");
    s->connect(d.events());
  }

  // Everybody listed may ask for the status.
  for (const auto* key : {&k.scanner, &k.viewer, &k.admin})
    EXPECT_EQ(d.type_of(key, make_status_request("s")), MessageType::kStatusReply);

  // Only admin loads the preop; the refusal comes before the request is
  // interpreted (a scanner's malformed preop.load is unauthorised, not invalid).
  EXPECT_EQ(d.error_of(&k.scanner, atlas_request("p")), ErrorCode::kUnauthorised);
  EXPECT_EQ(d.error_of(&k.viewer, atlas_request("p")), ErrorCode::kUnauthorised);
  Message no_frames = make_preop_load_request("bad", {});
  EXPECT_EQ(d.error_of(&k.scanner, no_frames), ErrorCode::kUnauthorised);
  EXPECT_EQ(d.error_of(&k.admin, no_frames), ErrorCode::kInvalidRequest);
  ASSERT_EQ(d.type_of(&k.admin, atlas_request("p")), MessageType::kPreopLoadReply);
  for (int i = 0; i < 500; ++i) {
    const auto s = parse_status_reply(*d.call(&k.viewer, make_status_request("s")));
    if (s.state == ServerState::kReady) break;
    std::this_thread::sleep_for(10ms);
  }

  // The viewer may not push; the scanner may.
  EXPECT_EQ(d.error_of(&k.viewer, push_request("v")), ErrorCode::kUnauthorised);
  const auto pushed = d.call(&k.scanner, push_request("p1"));
  ASSERT_TRUE(pushed && pushed->type() == MessageType::kScanPushReply) << (pushed ? pushed->header.dump() : "none");
  const std::string scan_id = parse_scan_push_reply(*pushed).scan_id;

  // Both pull the result once it is done, and both list.
  const Message result = make_scan_result_request("r", {scan_id, {ResultPart::kDisplacement}, {}});
  std::optional<Message> done;
  for (int i = 0; i < 500; ++i) {
    done = d.call(&k.viewer, result);
    if (done && done->type() == MessageType::kScanResultReply) break;
    std::this_thread::sleep_for(10ms);
  }
  ASSERT_TRUE(done && done->type() == MessageType::kScanResultReply) << done->header.dump();
  EXPECT_NE(parse_scan_result_reply(*done).find("displacement"), nullptr);  // durable before scan.done
  EXPECT_EQ(d.type_of(&k.scanner, result), MessageType::kScanResultReply);
  for (const auto* key : {&k.scanner, &k.viewer})
    EXPECT_EQ(parse_scan_list_reply(*d.call(key, make_scan_list_request("l", {10}))).scans.size(), 1u);

  // Strangers get nothing at all: an unknown key, and a client without CURVE.
  EXPECT_FALSE(d.call(&k.stranger, make_status_request("x"), 1500ms).has_value());
  EXPECT_FALSE(d.call(nullptr, make_status_request("x"), 1500ms).has_value());
  EXPECT_EQ(d.type_of(&k.scanner, make_status_request("still")), MessageType::kStatusReply);

  // The allowed subscriber saw the scan's events; the stranger saw none.
  bool saw_done = false;
  while (auto e = tp::receive_event(*viewer_sub, Limits::client_inbound(), 200ms))
    if (e->type() == MessageType::kEventScanDone) saw_done = parse_scan_done_event(*e).scan_id == scan_id;
  EXPECT_TRUE(saw_done) << "event.scan.done did not reach the viewer over CURVE";
  EXPECT_FALSE(tp::receive_event(*stranger_sub, Limits::client_inbound(), 200ms).has_value());

  // Only admin stops the daemon.
  EXPECT_EQ(d.error_of(&k.scanner, make_shutdown_request("s")), ErrorCode::kUnauthorised);
  EXPECT_EQ(d.error_of(&k.viewer, make_shutdown_request("s")), ErrorCode::kUnauthorised);
  EXPECT_EQ(d.type_of(&k.admin, make_shutdown_request("s")), MessageType::kShutdownReply);
  EXPECT_EQ(d.join(), 0);
}

// Many strangers at once (unknown keys, no CURVE, a wrong server key) get
// nothing, and a listed client is served among them.
TEST(DaemonSecurity, StrangersDoNotStopTheOthersBeingServed) {
  // Capture the daemon's log to check what it says about the strangers.
  auto sink = std::make_shared<spdlog::sinks::ringbuffer_sink_mt>(10000);
  auto previous = spdlog::default_logger();
  spdlog::set_default_logger(std::make_shared<spdlog::logger>("capture", sink));
  struct Restore {
    std::shared_ptr<spdlog::logger> logger;
    ~Restore() { spdlog::set_default_logger(logger); }
  } restore{previous};
  CurveDaemon d;
  const Keys& k = d.keys();
  constexpr int kEach = 20;
  std::vector<std::unique_ptr<zmq::socket_t>> strangers;
  std::vector<curve::KeyPair> unknown(kEach);
  const curve::KeyPair fake_server = curve::generate_key_pair();
  for (int i = 0; i < kEach; ++i) {
    unknown[i] = curve::generate_key_pair();
    strangers.push_back(d.socket(zmq::socket_type::dealer, &unknown[i]));  // unknown key
    strangers.push_back(d.socket(zmq::socket_type::dealer, nullptr));      // no CURVE
    auto wrong = d.socket(zmq::socket_type::dealer, nullptr);              // trusts another server key
    curve::set_client_options(*wrong, {fake_server.public_z85, k.scanner});
    strangers.push_back(std::move(wrong));
  }
  for (auto& s : strangers) {
    s->connect(d.endpoint());
    tp::send_request(*s, make_status_request("stranger"));
  }
  int served = 0;
  for (int i = 0; i < 10; ++i) served += d.type_of(&k.scanner, make_status_request("s")) == MessageType::kStatusReply;
  EXPECT_EQ(served, 10);
  int answered = 0;
  for (auto& s : strangers) answered += tp::receive_reply(*s, Limits::client_inbound(), 20ms).has_value();
  EXPECT_EQ(answered, 0) << "a stranger got a reply";
  std::printf("%zu stranger connections (unknown key, no CURVE, wrong server key): %d answered; 10/10 scanner "
              "requests served among them\n", strangers.size(), answered);
  EXPECT_EQ(d.type_of(&k.admin, make_shutdown_request("s")), MessageType::kShutdownReply);
  EXPECT_EQ(d.join(), 0);

  // Unknown keys are logged by fingerprint, once each; handshakes that never
  // reach the ZAP handler are counted, rate-limited; no secret is ever logged.
  int refused_lines = 0, failed_lines = 0;
  for (const std::string& line : sink->last_formatted()) {
    refused_lines += line.find("key not in the allow-list") != std::string::npos;
    failed_lines += line.find("failed the CURVE handshake") != std::string::npos;
    const std::initializer_list<const curve::KeyPair*> secrets = {&k.server, &k.scanner, &k.admin, &unknown[0],
                                                                  &unknown[kEach - 1]};
    for (const curve::KeyPair* secret : secrets)
      EXPECT_EQ(line.find(secret->secret_z85), std::string::npos) << line;
  }
  EXPECT_GE(refused_lines, 1);
  EXPECT_LE(refused_lines, kEach);
  EXPECT_GE(failed_lines, 1);
  EXPECT_LE(failed_lines, 2);  // once a minute per socket
  std::printf("log: %d refused-key lines, %d handshake-failure lines\n", refused_lines, failed_lines);
}

// The ZAP handler's verdict reaches each message as User-Id (the role) and the
// allow-list name, through transport::receive_request.
TEST(DaemonSecurity, ZapUserIdAndNameReachTheRequest) {
  test::TempDir dir;
  const curve::KeyPair server = curve::generate_key_pair(), scanner = curve::generate_key_pair();
  zmq::context_t ctx(1);
  std::map<std::string, AllowedClient> allowed = {
      {curve::z85_to_binary(scanner.public_z85), {"or1-scanner", Role::scanner, scanner.public_z85}}};
  ZapHandler zap(ctx, allowed);
  zmq::socket_t router(ctx, zmq::socket_type::router);
  router.set(zmq::sockopt::linger, 0);
  curve::set_server_options(router, server.secret_z85, kRequestsZapDomain);
  router.bind("tcp://127.0.0.1:*");
  zmq::socket_t dealer(ctx, zmq::socket_type::dealer);
  dealer.set(zmq::sockopt::linger, 0);
  curve::set_client_options(dealer, {server.public_z85, scanner});
  dealer.connect(router.get(zmq::sockopt::last_endpoint));
  tp::send_request(dealer, make_status_request("who"));
  const auto request = tp::receive_request(router, 5000ms);
  ASSERT_TRUE(request.has_value());
  EXPECT_EQ(request->user_id.value_or("none"), "scanner");
  EXPECT_EQ(request->client_name.value_or("none"), "or1-scanner");
  EXPECT_EQ(zap.accepted(), 1u);
  EXPECT_EQ(zap.refused(), 0u);
  const Peer peer = Peer::from_zap(request->user_id, request->client_name);
  EXPECT_EQ(peer.role, Role::scanner);
  EXPECT_EQ(peer.name, "or1-scanner");
}

}  // namespace
