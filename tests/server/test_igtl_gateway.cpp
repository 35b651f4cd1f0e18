// The OpenIGTLink gateway in-process, over real loopback sockets, with a real
// case store and a receiver on the library's own client socket.
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <thread>

#include <nlohmann/json.hpp>

#include "core/errors.h"
#include "igtl_receiver.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "server/igtl_gateway.h"
#include "igtl_test_store.h"
#include "test_support.h"

using namespace brainshift;
using namespace brainshift::server;
using namespace std::chrono_literals;
using test::IgtlReceived;
using test::IgtlReceiver;
using test::any_port;
using test::store_result;

namespace {

std::string status_scan(const std::vector<IgtlReceived>& result) {
  return nlohmann::json::parse(result.back().status()->GetStatusString()).at("scan_id");
}

void wait_clients(const IgtlGateway& g, std::uint64_t n) {
  const auto until = std::chrono::steady_clock::now() + 10s;
  while (g.info().clients != n && std::chrono::steady_clock::now() < until) std::this_thread::sleep_for(5ms);
  ASSERT_EQ(g.info().clients, n);
}

}  // namespace

TEST(IgtlGateway, LatestResultOnConnectThenEveryNewResultToEveryClient) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string first = store_result(store, 1.5f);
  IgtlGateway gateway(any_port(), store, config::default_label_table());
  ASSERT_GT(gateway.port(), 0);

  IgtlReceiver a(gateway.port(), 10s);
  const auto on_connect = a.next_result();
  EXPECT_EQ(status_scan(on_connect), first);
  std::vector<std::string> devices;
  for (const auto& m : on_connect) devices.push_back(m.device);
  EXPECT_EQ(devices, (std::vector<std::string>{"bs.field", "bs.warped_image", "bs.warped_labels", "bs.model.brain",
                                               "bs.model.tumor", "bs.status"}));
  ASSERT_NE(on_connect[0].image(), nullptr);
  const auto* v = static_cast<const float*>(on_connect[0].image()->GetScalarPointer());
  EXPECT_EQ(v[0], 1.5f);
  EXPECT_EQ(v[1], -1.5f);
  EXPECT_EQ(v[2], 3.0f);

  const std::string second = store_result(store, 2.5f, 12, {protocol::ResultKind::affine_only_fallback, "Jacobian folded"});
  gateway.publish(second);
  const auto pushed = a.next_result();
  EXPECT_EQ(status_scan(pushed), second);
  EXPECT_EQ(std::string(pushed.back().status()->GetErrorName()), "affine_fallback");
  EXPECT_EQ(nlohmann::json::parse(pushed.back().status()->GetStatusString()).at("reason"), "Jacobian folded");

  IgtlReceiver late(gateway.port(), 10s);
  EXPECT_EQ(status_scan(late.next_result()), second);
  wait_clients(gateway, 2);
  // A message counts as sent when send() has returned, which may be after
  // the receiver already read it (seen under load: 17 here).
  const auto until = std::chrono::steady_clock::now() + 10s;
  while (gateway.info().messages_sent < 18u && std::chrono::steady_clock::now() < until)
    std::this_thread::sleep_for(5ms);
  const auto info = gateway.info();
  EXPECT_EQ(info.port, static_cast<std::uint64_t>(gateway.port()));
  EXPECT_EQ(info.messages_sent, 18u);
  EXPECT_EQ(info.messages_dropped, 0u);
}

TEST(IgtlGateway, ClientVanishingMidMessageDisturbsNobody) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  store_result(store, 1.0f, 40);  // a field of 768 KB: the peer leaves inside it
  IgtlGateway gateway(any_port(), store, config::default_label_table());
  IgtlReceiver steady(gateway.port(), 10s);
  steady.next_result();

  const int rude = test::raw_igtl_connect(gateway.port());
  char buf[1000];
  std::size_t got = 0;
  while (got < sizeof buf) {
    const ssize_t n = ::recv(rude, buf + got, sizeof buf - got, 0);
    ASSERT_GT(n, 0);
    got += static_cast<std::size_t>(n);
  }
  EXPECT_EQ(std::string(buf + 2, 5), "IMAGE");
  ::close(rude);

  const std::string next = store_result(store, 4.0f, 40);
  gateway.publish(next);
  EXPECT_EQ(status_scan(steady.next_result()), next);
  wait_clients(gateway, 1);
  IgtlReceiver after(gateway.port(), 10s);
  EXPECT_EQ(status_scan(after.next_result()), next);
}

TEST(IgtlGateway, SlowClientLosesTheOldestMessagesNeverTheStream) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string scan = store_result(store, 3.0f, 72);  // 4.5 MB field per result
  IgtlGateway gateway(any_port(8), store, config::default_label_table());
  IgtlReceiver slow(gateway.port(), 10s);  // does not read until the end
  IgtlReceiver fast(gateway.port(), 10s);
  fast.next_result();
  const std::string last = store_result(store, 9.0f, 72);
  for (int i = 0; i < 12; ++i) {
    gateway.publish(i == 11 ? last : scan);
    // The fast client keeps up, whatever the slow one does.
    EXPECT_EQ(status_scan(fast.next_result()), i == 11 ? last : scan);
  }
  EXPECT_GT(gateway.info().messages_dropped, 0u);
  // What the slow client finally reads is whole messages (each unpacks with
  // its CRC), ending with the latest result's status.
  std::vector<IgtlReceived> got;
  while (auto m = slow.next()) {
    got.push_back(*m);
    if (m->type == "STATUS" && status_scan({*m}) == last) break;
  }
  ASSERT_FALSE(got.empty());
  EXPECT_EQ(got.back().type, "STATUS");
  EXPECT_EQ(status_scan({got.back()}), last);
  EXPECT_LT(got.size(), 13u * 6);
  // Superseded results were dropped, the latest one arrives whole.
  ASSERT_GE(got.size(), 6u);
  const std::vector<IgtlReceived> latest(got.end() - 6, got.end());
  std::vector<std::string> devices;
  for (const auto& m : latest) devices.push_back(m.device);
  EXPECT_EQ(devices, (std::vector<std::string>{"bs.field", "bs.warped_image", "bs.warped_labels", "bs.model.brain",
                                               "bs.model.tumor", "bs.status"}));
  ASSERT_NE(latest[0].image(), nullptr);
  EXPECT_EQ(static_cast<const float*>(latest[0].image()->GetScalarPointer())[0], 9.0f);
}

TEST(IgtlGateway, WhatAClientSendsIsReadAndIgnored) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string scan = store_result(store, 1.0f);
  IgtlGateway gateway(any_port(), store, config::default_label_table());
  IgtlReceiver chatty(gateway.port(), 10s);
  // Slicer may send messages of its own; garbage must not confuse the gateway either.
  const std::string noise(1 << 20, '\x5a');
  ASSERT_EQ(chatty.socket().Send(noise.data(), static_cast<int>(noise.size())), 1);
  EXPECT_EQ(status_scan(chatty.next_result()), scan);
  gateway.publish(scan);
  EXPECT_EQ(status_scan(chatty.next_result()), scan);
  wait_clients(gateway, 1);
}

TEST(IgtlGateway, ConnectionsBeyondMaxClientsAreClosed) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  store_result(store, 1.0f);
  IgtlGateway gateway(any_port(32, 1), store, config::default_label_table());
  IgtlReceiver first(gateway.port(), 10s);
  first.next_result();
  const int extra = test::raw_igtl_connect(gateway.port());
  char c;
  EXPECT_EQ(::recv(extra, &c, 1, 0), 0);  // closed without a byte
  ::close(extra);
  wait_clients(gateway, 1);
}

TEST(IgtlGateway, PortInUseIsAClearError) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  IgtlGateway one(any_port(), store, config::default_label_table());
  OpenIgtlinkSettings same = any_port();
  same.port = one.port();
  try {
    IgtlGateway two(same, store, config::default_label_table());
    FAIL() << "listened twice on one port";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("127.0.0.1:" + std::to_string(one.port())), std::string::npos) << e.what();
  }
}

TEST(IgtlGateway, ReadsBackWhatTheStoreHolds) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string scan = store_result(store, 0.75f);
  const auto r = load_igtl_result(store, scan, config::default_label_table());
  ASSERT_TRUE(r.field && r.warped_image && r.warped_labels);
  EXPECT_TRUE(r.field->grid.same_geometry(test::small_grid(12)));
  EXPECT_EQ(r.field->vectors[5], Eigen::Vector3f(0.75f, -0.75f, 1.5f));
  ASSERT_EQ(r.models.size(), 2u);
  EXPECT_EQ(r.models[0].first, "brain");
  EXPECT_EQ(r.models[1].first, "tumor");
  EXPECT_TRUE(r.problems.empty());
  EXPECT_THROW(load_igtl_result(store, "s-999999", config::default_label_table()), InputError);
}
