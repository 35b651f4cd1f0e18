// Real ZeroMQ round trips through transport.h: DEALER and REQ clients against
// a ROUTER served by a thread, PUB/SUB events, and the hard frame cap.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <thread>

#include "protocol/events.h"
#include "protocol/media.h"
#include "protocol/requests.h"
#include "protocol/transport.h"
#include "test_util.h"

namespace bp = brainshift::protocol;
namespace tp = brainshift::protocol::transport;
using bp::ErrorCode;
using namespace std::chrono_literals;

namespace {

// A minimal server: answers status and scan.push, and every bad request with
// a typed error, the way brainshiftd must. It records the labels it received.
class TestServer {
 public:
  TestServer(zmq::context_t& ctx, const std::string& endpoint, bp::Limits limits = {})
      : router_(ctx, zmq::socket_type::router), limits_(limits) {
    router_.set(zmq::sockopt::linger, 0);
    tp::apply_hard_frame_cap(router_, limits_);
    router_.bind(endpoint);
    endpoint_ = router_.get(zmq::sockopt::last_endpoint);
    thread_ = std::thread([this] { run(); });
  }
  ~TestServer() {
    stop_ = true;
    thread_.join();
  }
  const std::string& endpoint() const { return endpoint_; }
  std::string last_labels() {
    std::lock_guard lock(mutex_);
    return last_labels_;
  }

 private:
  void run() {
    while (!stop_) {
      auto req = tp::receive_request(router_, 20ms);
      if (!req || req->envelope.routing.empty()) continue;
      tp::send_reply(router_, req->envelope, answer(std::move(req->wire)));
    }
  }
  bp::Message answer(tp::Wire wire) {
    try {
      const bp::Message m = bp::decode(std::move(wire), limits_);
      switch (m.type()) {
        case bp::MessageType::kStatus:
          bp::parse_status_request(m);
          return bp::make_status_reply(m.request_id(), {.state = bp::ServerState::kReady});
        case bp::MessageType::kScanPush: {
          const auto push = bp::parse_scan_push_request(m);
          std::lock_guard lock(mutex_);
          last_labels_ = push.labels.value().bytes;
          return bp::make_scan_push_reply(m.request_id(), {"s-000001", false});
        }
        default:
          return bp::make_error_reply(m.request_id(), ErrorCode::kInvalidRequest, "not served here");
      }
    } catch (const bp::ProtocolError& e) {
      return bp::make_error_reply(e);
    }
  }

  zmq::socket_t router_;
  bp::Limits limits_;
  std::string endpoint_;
  std::atomic<bool> stop_{false};
  std::mutex mutex_;
  std::string last_labels_;
  std::thread thread_;
};

zmq::socket_t connect(zmq::context_t& ctx, zmq::socket_type type, const std::string& endpoint) {
  zmq::socket_t s(ctx, type);
  s.set(zmq::sockopt::linger, 0);
  s.connect(endpoint);
  return s;
}

bp::Message must_reply(zmq::socket_t& client) {
  auto reply = tp::receive_reply(client, bp::Limits::client_inbound(), 5000ms);
  if (!reply) throw std::runtime_error("no reply within 5 s");
  return std::move(*reply);
}

bp::Frame labels_with_nuls() {
  bp::Frame f = bp::media::nifti_frame("labels", bp::testing::fake_nifti(16, 16, 16));
  EXPECT_NE(f.bytes.find('\0', 400), std::string::npos);
  return f;
}

}  // namespace

TEST(Transport, DealerRouterRoundTripOverTcpKeepsBinaryFrames) {
  zmq::context_t ctx;
  TestServer server(ctx, "tcp://127.0.0.1:*");
  auto dealer = connect(ctx, zmq::socket_type::dealer, server.endpoint());

  const bp::Frame labels = labels_with_nuls();
  tp::send_request(dealer, bp::make_scan_push_request("push-1", {labels, std::nullopt, "c-1"}));
  const auto reply = must_reply(dealer);
  EXPECT_EQ(reply.request_id(), "push-1");
  EXPECT_EQ(bp::parse_scan_push_reply(reply).scan_id, "s-000001");
  EXPECT_EQ(server.last_labels(), labels.bytes);

  tp::send_request(dealer, bp::make_status_request("st-1"));
  const auto status = must_reply(dealer);
  EXPECT_EQ(status.request_id(), "st-1");
  EXPECT_EQ(bp::parse_status_reply(status).state, bp::ServerState::kReady);
}

TEST(Transport, ReqClientWorksOverInproc) {
  zmq::context_t ctx;
  TestServer server(ctx, "inproc://brainshift-test");
  auto req = connect(ctx, zmq::socket_type::req, server.endpoint());
  tp::send_request(req, bp::make_status_request("req-1"));
  const auto reply = must_reply(req);
  EXPECT_EQ(reply.request_id(), "req-1");
  EXPECT_EQ(reply.type(), bp::MessageType::kStatusReply);
}

TEST(Transport, BadRequestsGetTypedErrorsAndTheServerKeepsServing) {
  zmq::context_t ctx;
  TestServer server(ctx, "tcp://127.0.0.1:*");
  auto dealer = connect(ctx, zmq::socket_type::dealer, server.endpoint());

  tp::send_wire(dealer, {"", "{not json"});
  auto reply = must_reply(dealer);
  EXPECT_EQ(bp::parse_error_reply(reply).code, ErrorCode::kMalformedJson);
  EXPECT_EQ(reply.request_id(), "");

  auto wire = bp::encode(bp::make_scan_push_request("short-1", {labels_with_nuls()}));
  wire.pop_back();  // header declares a frame that is not sent
  wire.insert(wire.begin(), "");
  tp::send_wire(dealer, wire);
  reply = must_reply(dealer);
  EXPECT_EQ(bp::parse_error_reply(reply).code, ErrorCode::kFrameCountMismatch);
  EXPECT_EQ(reply.request_id(), "short-1");

  tp::send_wire(dealer, {"", R"({"v":2,"type":"status","request_id":"v2-client"})"});
  reply = must_reply(dealer);
  EXPECT_EQ(bp::parse_error_reply(reply).code, ErrorCode::kVersionMismatch);
  EXPECT_EQ(reply.request_id(), "v2-client");

  tp::send_request(dealer, bp::make_status_request("after-errors"));
  EXPECT_EQ(must_reply(dealer).type(), bp::MessageType::kStatusReply);
}

TEST(Transport, FramesOverTheLimitGetTooLargeAndOverTheHardCapAreDropped) {
  zmq::context_t ctx;
  bp::Limits limits;
  limits.max_frame_bytes = 4096;
  limits.max_header_bytes = 2048;  // hard cap = 2 x the larger of the two = 8192
  TestServer server(ctx, "tcp://127.0.0.1:*", limits);

  auto dealer = connect(ctx, zmq::socket_type::dealer, server.endpoint());
  bp::Frame big = bp::media::nifti_frame("labels", bp::testing::fake_nifti(16, 16, 20));  // 5472 B
  tp::send_request(dealer, bp::make_scan_push_request("big-1", {big}));
  const auto reply = must_reply(dealer);
  EXPECT_EQ(bp::parse_error_reply(reply).code, ErrorCode::kTooLarge);
  EXPECT_EQ(reply.request_id(), "big-1");

  // Above the cap libzmq drops the connection before allocating: no reply.
  auto greedy = connect(ctx, zmq::socket_type::dealer, server.endpoint());
  bp::Frame huge = bp::media::nifti_frame("labels", bp::testing::fake_nifti(32, 32, 32));  // 33 kB
  tp::send_request(greedy, bp::make_scan_push_request("huge-1", {huge}));
  EXPECT_FALSE(tp::receive_reply(greedy, bp::Limits::client_inbound(), 500ms).has_value());

  // Other clients are unaffected.
  auto polite = connect(ctx, zmq::socket_type::dealer, server.endpoint());
  tp::send_request(polite, bp::make_status_request("polite-1"));
  EXPECT_EQ(must_reply(polite).request_id(), "polite-1");
}

TEST(Transport, PubSubEventsWithTopicFiltering) {
  zmq::context_t ctx;
  zmq::socket_t pub(ctx, zmq::socket_type::pub);
  pub.set(zmq::sockopt::linger, 0);
  pub.bind("inproc://brainshift-events");
  zmq::socket_t sub(ctx, zmq::socket_type::sub);
  sub.set(zmq::sockopt::linger, 0);
  sub.set(zmq::sockopt::subscribe, "event.scan.");
  sub.connect("inproc://brainshift-events");

  // PUB drops messages until the subscription has arrived: publish until seen.
  const bp::ScanDoneEvent done{"s-000001", "c-1", 2.5};
  std::optional<bp::Message> got;
  for (int i = 0; i < 100 && !got; ++i) {
    tp::publish(pub, bp::make_event(bp::StageEvent{
                         {bp::StageScope::kIntraop, "s-000001", "", "solve", 0.1, bp::utc_now()}}));
    tp::publish(pub, bp::make_event(done));
    got = tp::receive_event(sub, {}, 20ms);
  }
  ASSERT_TRUE(got.has_value());
  EXPECT_EQ(got->type(), bp::MessageType::kEventScanDone);  // stage events filtered out
  EXPECT_EQ(bp::parse_scan_done_event(*got), done);
}

// Real MRI bytes (Colin27, gzipped NIfTI-1, several MB) go through unchanged
// and are recognised as gzip NIfTI by content.
TEST(Transport, RealGzippedNiftiTravelsByteExact) {
  const char* path = "/usr/share/mricron/templates/ch2bet.nii.gz";
  std::ifstream in(path, std::ios::binary);
  if (!in) GTEST_SKIP() << path << " is not installed (Debian package mricron-data)";
  const std::string bytes{std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
  ASSERT_GT(bytes.size(), 1000000u);
  const bp::Frame labels = bp::media::nifti_frame("labels", bytes);
  EXPECT_EQ(labels.media_type, bp::media::kNiftiGz);
  EXPECT_NO_THROW(bp::media::check_content(labels));

  zmq::context_t ctx;
  TestServer server(ctx, "tcp://127.0.0.1:*");
  auto dealer = connect(ctx, zmq::socket_type::dealer, server.endpoint());
  const auto start = std::chrono::steady_clock::now();
  tp::send_request(dealer, bp::make_scan_push_request("real-1", {labels, std::nullopt, "ch2bet"}));
  const auto reply = must_reply(dealer);
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  EXPECT_EQ(bp::parse_scan_push_reply(reply).scan_id, "s-000001");
  EXPECT_EQ(server.last_labels(), bytes);
  std::printf("ch2bet.nii.gz (%zu bytes) scan.push round trip over tcp loopback: %.1f ms\n",
              bytes.size(), ms);
}
