#include "server/server_core.h"

#include <algorithm>
#include <cstdio>
#include <future>
#include <random>
#include <thread>

#include <spdlog/spdlog.h>

#include "core/errors.h"
#include "image/label_placement.h"
#include "image/nifti_io.h"
#include "protocol/events.h"
#include "protocol/version.h"
#include "server/server_core_internal.h"

namespace brainshift::server {
namespace fs = std::filesystem;
using namespace protocol;

std::string new_preop_id() {
  std::random_device rd;
  char buf[64];
  const std::string t = utc_now();  // 2024-05-01T12:34:56.789Z
  std::string compact;
  for (char c : t)
    if (std::isdigit(static_cast<unsigned char>(c))) compact += c;
  std::snprintf(buf, sizeof buf, "preop-%s-%04x", compact.substr(0, 14).c_str(), rd() & 0xffff);
  return buf;
}


namespace {

bool valid_stage_name(const std::string& s) {
  if (s.empty() || s.size() > 32) return false;
  for (char c : s)
    if (!(c == '_' || (c >= 'a' && c <= 'z'))) return false;
  return true;
}

}  // namespace

ServerCore::ServerCore(ServerSettings settings, CaseStore& store, EnginePort& engine, EventSink events,
                       std::map<std::string, std::string> versions)
    : settings_(std::move(settings)),
      store_(store),
      engine_(engine),
      events_(std::move(events)),
      versions_(std::move(versions)),
      queue_(settings_.queue_depth) {
  limits_ = Limits::server_inbound();
  limits_.max_frame_bytes = settings_.max_frame_bytes;
  limits_.max_total_bytes = std::max(limits_.max_total_bytes, 2 * settings_.max_frame_bytes);
  versions_["protocol"] = std::to_string(kProtocolVersion);
  try {
    timing_log_ = std::make_unique<TimingLogFile>(settings_.timing_log_path().string());
  } catch (const std::exception& e) {
    // Timings still go out as events; losing the file must not stop surgery.
    spdlog::error("timing log {} unusable: {}", settings_.timing_log_path().string(), e.what());
  }
}

ServerCore::~ServerCore() = default;

StatusReply ServerCore::status() const {
  StatusReply r;
  std::lock_guard lock(mutex_);
  r.state = state_;
  r.progress = state_ == ServerState::kLoadingPreop ? progress_ : std::nullopt;
  r.versions = versions_;
  if (!loading_preop_id_.empty()) r.preop_id = loading_preop_id_, r.preop_patient_id = loading_patient_id_;
  else if (!ready_preop_id_.empty()) r.preop_id = ready_preop_id_, r.preop_patient_id = ready_patient_id_;
  r.mesh = mesh_size_;
  r.mpi_ranks = static_cast<std::uint64_t>(ranks_);
  r.queue = {queue_.size(), queue_.capacity()};
  if (state_ == ServerState::kProcessing) r.current_scan_id = current_scan_;
  r.last_error = last_error_;
  return r;
}

ServerCore::DecodedScan ServerCore::decode_scan(const PushedScan& input) const {
  const auto t0 = Clock::now();
  DecodedScan d;
  const std::size_t max_bytes = engine_.max_image_bytes();
  // The two frames inflate side by side: the push is acknowledged only after
  // both decoded, and the scan waits for the acknowledgement.
  std::future<ImageF> image;
  if (input.image_bytes)
    image = std::async(std::launch::async,
                       [&] { return scalar_image_from_bytes(*input.image_bytes, "image", max_bytes); });
  if (input.labels_bytes) d.labels = label_image_from_bytes(*input.labels_bytes, "labels", max_bytes);
  if (image.valid()) {
    d.image = image.get();
    if (d.labels) d.labels = labels_on_image_grid(std::move(*d.labels), d.image->grid, "labels");
  }
  if (input.labels_use) d.labels_use = given_labels_use_from_string(*input.labels_use);
  d.read_seconds = seconds_since(t0);
  return d;
}

void ServerCore::emit(Message event) {
  try {
    events_(std::move(event));
  } catch (const std::exception& e) {
    spdlog::warn("event not published: {}", e.what());
  }
}

void ServerCore::log_stage(StageTiming timing) {
  if (!valid_stage_name(timing.stage)) return;
  timing.t = utc_now();
  try {
    if (timing_log_) timing_log_->write(timing);
  } catch (const std::exception& e) {
    spdlog::warn("timing log: {}", e.what());
  }
  emit(make_event(StageEvent{timing}));
}

void ServerCore::request_stop() {
  stopping_ = true;
  queue_.close();
}

bool ServerCore::step(std::chrono::milliseconds wait) {
  if (stopping_) return false;
  std::unique_ptr<PreopJob> job;
  {
    std::lock_guard lock(mutex_);
    job = std::move(pending_preop_);
  }
  if (job) {
    run_preop_job(std::move(*job));
    return true;
  }
  {
    std::lock_guard lock(mutex_);
    if (ready_preop_id_.empty() || !loading_preop_id_.empty()) wait = std::min(wait, std::chrono::milliseconds(20));
  }
  // Scans wait while no preop is warm (e.g. restart before the warm-up ends).
  if (!engine_.ready()) {
    std::this_thread::sleep_for(wait);
    return false;
  }
  if (!repairs_.empty()) {
    const std::string id = repairs_.back();
    repairs_.pop_back();
    repair_scan(id);
    return true;
  }
  auto scan_id = queue_.take(wait);
  if (!scan_id) return false;
  run_scan(*scan_id);
  return true;
}

}  // namespace brainshift::server
