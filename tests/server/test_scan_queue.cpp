#include <gtest/gtest.h>

#include <thread>

#include "server/scan_queue.h"

using namespace brainshift::server;
using namespace std::chrono_literals;

TEST(ScanQueue, BoundedFifoRefusesBeyondCapacity) {
  ScanQueue q(2);
  EXPECT_TRUE(q.has_room());
  EXPECT_TRUE(q.offer("a"));
  EXPECT_TRUE(q.offer("b"));
  EXPECT_FALSE(q.has_room());
  EXPECT_FALSE(q.offer("c"));
  EXPECT_EQ(q.size(), 2u);
  EXPECT_EQ(q.take(0ms).value(), "a");
  EXPECT_TRUE(q.offer("c"));
  EXPECT_EQ(q.take(0ms).value(), "b");
  EXPECT_EQ(q.take(0ms).value(), "c");
  EXPECT_FALSE(q.take(10ms).has_value());
}

TEST(ScanQueue, RestoreIgnoresCapacity) {
  ScanQueue q(1);
  q.restore("old1");
  q.restore("old2");
  EXPECT_EQ(q.size(), 2u);
  EXPECT_FALSE(q.offer("new"));
  EXPECT_EQ(q.take(0ms).value(), "old1");
}

TEST(ScanQueue, TakeWakesOnOfferAndOnClose) {
  ScanQueue q(4);
  std::thread producer([&] {
    std::this_thread::sleep_for(20ms);
    q.offer("x");
  });
  EXPECT_EQ(q.take(5s).value(), "x");
  producer.join();
  std::thread closer([&] {
    std::this_thread::sleep_for(20ms);
    q.close();
  });
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_FALSE(q.take(5s).has_value());
  EXPECT_LT(std::chrono::steady_clock::now() - t0, 2s);
  closer.join();
  EXPECT_FALSE(q.offer("y"));
}

TEST(ScanQueue, ZeroCapacityIsRefused) { EXPECT_THROW(ScanQueue(0), std::invalid_argument); }
