#pragma once
// The bounded queue of scans waiting for the engine. The socket thread offers
// scans (busy when full: never a silent drop); the engine thread takes them.
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <deque>
#include <mutex>
#include <optional>
#include <string>

namespace brainshift::server {

class ScanQueue {
 public:
  explicit ScanQueue(std::size_t capacity);

  // Whether offer() would succeed now. The socket thread is the only producer,
  // so a true answer stays true until its own offer().
  bool has_room() const;
  // False (and nothing queued) when full.
  bool offer(const std::string& scan_id);
  // Re-queues acknowledged scans found in the store after a restart. They were
  // accepted once, so they are never refused, even beyond the capacity.
  void restore(const std::string& scan_id);
  // Waits up to `wait` for a scan; nullopt on timeout or after close().
  std::optional<std::string> take(std::chrono::milliseconds wait);
  void close();  // wakes take(); later offers fail

  std::size_t size() const;
  std::size_t capacity() const { return capacity_; }

 private:
  const std::size_t capacity_;
  mutable std::mutex mutex_;
  std::condition_variable ready_;
  std::deque<std::string> scans_;
  bool closed_ = false;
};

}  // namespace brainshift::server
