#include "server/scan_queue.h"

#include <stdexcept>

namespace brainshift::server {

ScanQueue::ScanQueue(std::size_t capacity) : capacity_(capacity) {
  if (capacity == 0) throw std::invalid_argument("scan queue capacity must be >= 1");
}

bool ScanQueue::has_room() const {
  std::lock_guard lock(mutex_);
  return !closed_ && scans_.size() < capacity_;
}

bool ScanQueue::offer(const std::string& scan_id) {
  {
    std::lock_guard lock(mutex_);
    if (closed_ || scans_.size() >= capacity_) return false;
    scans_.push_back(scan_id);
  }
  ready_.notify_one();
  return true;
}

void ScanQueue::restore(const std::string& scan_id) {
  {
    std::lock_guard lock(mutex_);
    scans_.push_back(scan_id);
  }
  ready_.notify_one();
}

std::optional<std::string> ScanQueue::take(std::chrono::milliseconds wait) {
  std::unique_lock lock(mutex_);
  if (!ready_.wait_for(lock, wait, [this] { return closed_ || !scans_.empty(); })) return std::nullopt;
  if (closed_ || scans_.empty()) return std::nullopt;
  std::string id = std::move(scans_.front());
  scans_.pop_front();
  return id;
}

void ScanQueue::close() {
  {
    std::lock_guard lock(mutex_);
    closed_ = true;
  }
  ready_.notify_all();
}

std::size_t ScanQueue::size() const {
  std::lock_guard lock(mutex_);
  return scans_.size();
}

}  // namespace brainshift::server
