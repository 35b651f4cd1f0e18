#include "server/server_core.h"

#include <algorithm>
#include <future>
#include <limits>
#include <chrono>
#include <thread>
#include <cstdio>
#include <random>

#include <spdlog/spdlog.h>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "protocol/events.h"
#include "protocol/media.h"
#include "protocol/version.h"
#include "server/preop_labels.h"
#include "server/result_files.h"

namespace brainshift::server {
namespace fs = std::filesystem;
using namespace protocol;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

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

// Share of the whole warm-up each preop stage takes (measured on the default
// atlas: meshing and factorisation dominate); only for the progress bar.
double preop_fraction(const std::string& stage, double stage_fraction) {
  static const std::vector<std::pair<std::string, double>> weights = {
      {"atlas", 0.05}, {"mesh", 0.45}, {"assemble", 0.10}, {"factorise", 0.35}, {"models", 0.05}};
  double before = 0.0;
  for (const auto& [name, w] : weights) {
    if (name == stage) return std::min(1.0, before + w * stage_fraction);
    before += w;
  }
  return before;  // unknown stage: report what is known to be done
}

bool valid_stage_name(const std::string& s) {
  if (s.empty() || s.size() > 32) return false;
  for (char c : s)
    if (!(c == '_' || (c >= 'a' && c <= 'z'))) return false;
  return true;
}

// Frames of the requested parts of a done scan, with every missing part in
// `unavailable` (e.g. no warped_image when the engine wrote none).
// deferred_pending: metrics.json, field.h5 and report.png are still being made (they follow
// scan.done, see ServerCore::add_deferred_outputs).
ScanResultReply collect_result_frames(const CaseStore& store, const ScanResultRequest& request,
                                      const ScanRecord& record, bool deferred_pending) {
  ScanResultReply reply;
  reply.scan_id = request.scan_id;
  auto add = [&](const std::string& frame, const std::vector<std::string>& files, const char* why_missing) {
    for (const auto& file : files) {
      auto bytes = store.read_result_file(request.scan_id, file);
      if (!bytes) continue;
      const std::string media = result_media_type(file, *bytes);
      reply.frames.push_back(Frame{frame, media, std::move(*bytes)});
      return true;
    }
    reply.unavailable.push_back({frame, why_missing});
    return false;
  };
  for (ResultPart part : request.parts) {
    if (part == ResultPart::kReport) {
      const char* why = !record.has_image ? "no intraop image was pushed (the report draws on it)"
                        : deferred_pending ? "report.png is being rendered; ask again shortly"
                                           : "report.png was not rendered (see the server log)";
      if (!add(frame_name(part), stored_file_names(part), why) && deferred_pending && record.has_image)
        reply.unavailable.back().pending = true;
    } else if (part == ResultPart::kDisplacementItk || part == ResultPart::kMetrics) {
      const char* why = deferred_pending ? "being written just after the field; ask again shortly" : "not in this result";
      if (!add(frame_name(part), stored_file_names(part), why) && deferred_pending)
        reply.unavailable.back().pending = true;
    } else if (part != ResultPart::kModels) {
      add(frame_name(part), stored_file_names(part),
          part == ResultPart::kWarpedImage ? "the engine wrote no warped image" : "not in this result");
    } else {
      const auto& wanted = request.structures.empty() ? all_structures() : request.structures;
      for (Structure s : wanted)
        add(model_frame_name(s), {model_file_name(s)}, "no model of this structure (label absent from the preop)");
    }
  }
  return reply;
}

}  // namespace

struct ServerCore::PreopJob {
  std::string preop_id;
  std::string source;  // "atlas", "files", "upload", "store"
  std::optional<PreopImages> images;  // absent: build the atlas / read files on the engine thread
  std::string label_table_json;
  std::optional<TetMesh> stored_mesh;
};

struct ServerCore::DecodedScan {
  LabelImage labels;
  std::optional<ImageF> image;
  double read_seconds = 0.0;
};

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

// ---------------------------------------------------------------- socket side

Message ServerCore::handle_wire(std::vector<std::string> wire, const Peer& peer) {
  try {
    return handle(decode(std::move(wire), limits_), peer);
  } catch (const ProtocolError& e) {
    spdlog::warn("refused a request: {} ({})", e.what(), to_string(e.code()));
    return make_error_reply(e);
  } catch (const std::exception& e) {
    spdlog::error("request could not be decoded: {}", e.what());
    return make_error_reply("", ErrorCode::kInternal, e.what());
  }
}

Message ServerCore::handle(const Message& m, const Peer& peer) {
  const std::string rid = m.request_id();
  try {
    if (auto why = refusal(peer, m.type(), settings_.security.allow_unauthenticated_shutdown)) {
      spdlog::warn("refused {} {} from {}: {}", to_string(m.type()), rid, peer.describe(), *why);
      return make_error_reply(rid, ErrorCode::kUnauthorised, *why);
    }
    switch (m.type()) {
      case MessageType::kStatus: return on_status(m);
      case MessageType::kPreopLoad: return on_preop_load(m);
      case MessageType::kScanPush: return on_scan_push(m);
      case MessageType::kScanResult: return on_scan_result(m);
      case MessageType::kScanList: return on_scan_list(m);
      case MessageType::kShutdown: return on_shutdown(m);
      default:
        return make_error_reply(rid, ErrorCode::kUnknownType,
                                "\"" + std::string(to_string(m.type())) + "\" is not a request");
    }
  } catch (const ProtocolError& e) {
    return make_error_reply(e, rid);
  } catch (const InputError& e) {
    return make_error_reply(rid, ErrorCode::kInvalidRequest, e.what());
  } catch (const std::exception& e) {
    spdlog::error("request {} failed: {}", rid, e.what());
    return make_error_reply(rid, ErrorCode::kInternal, e.what());
  }
}

StatusReply ServerCore::status() const {
  StatusReply r;
  std::lock_guard lock(mutex_);
  r.state = state_;
  r.progress = state_ == ServerState::kLoadingPreop ? progress_ : std::nullopt;
  r.versions = versions_;
  if (!loading_preop_id_.empty()) r.preop_id = loading_preop_id_;
  else if (!ready_preop_id_.empty()) r.preop_id = ready_preop_id_;
  r.mesh = mesh_size_;
  r.mpi_ranks = static_cast<std::uint64_t>(ranks_);
  r.queue = {queue_.size(), queue_.capacity()};
  if (state_ == ServerState::kProcessing) r.current_scan_id = current_scan_;
  r.last_error = last_error_;
  return r;
}

Message ServerCore::on_status(const Message& m) {
  parse_status_request(m);
  StatusReply r = status();
  if (status_extension_) status_extension_(r);  // outside mutex_
  return make_status_reply(m.request_id(), r);
}

Message ServerCore::on_preop_load(const Message& m) {
  PreopLoadRequest req = parse_preop_load_request(m);
  auto job = std::make_unique<PreopJob>();
  if (req.use_default_atlas) {
    job->source = "atlas";
  } else {
    const std::size_t max_bytes = engine_.max_image_bytes();
    PreopImages images;
    images.t1 = scalar_image_from_bytes(req.t1->bytes, "t1", max_bytes);
    images.labels = label_image_from_bytes(req.labels->bytes, "labels", max_bytes);
    if (!images.t1.grid.same_geometry(images.labels.grid))
      throw InputError("labels: grid differs from t1's (dims or world_from_voxel)");
    std::optional<LabelTable> table;
    if (req.label_table) {
      table = parse_label_table_json(req.label_table->bytes);
      job->label_table_json = req.label_table->bytes;
    }
    remap_preop_labels(images.labels, table ? &*table : nullptr);
    job->images = std::move(images);
    job->source = "upload";
  }
  std::lock_guard lock(mutex_);
  if (state_ == ServerState::kLoadingPreop || state_ == ServerState::kProcessing || pending_preop_ ||
      queue_.size() > 0)
    return make_error_reply(m.request_id(), ErrorCode::kBusy,
                            "a preop warm-up or scans are in progress; retry when the server is ready or idle");
  job->preop_id = new_preop_id();
  const std::string id = job->preop_id;
  loading_preop_id_ = id;
  state_ = ServerState::kLoadingPreop;
  progress_ = Progress{"queued", 0.0};
  pending_preop_ = std::move(job);
  spdlog::info("preop.load accepted: {} ({})", id, pending_preop_->source);
  return make_preop_load_reply(m.request_id(), {id});
}

ServerCore::DecodedScan ServerCore::decode_scan(const ScanInput& input) const {
  const auto t0 = Clock::now();
  DecodedScan d;
  const std::size_t max_bytes = engine_.max_image_bytes();
  // The two frames inflate side by side: the push is acknowledged only after
  // both decoded, and the scan waits for the acknowledgement.
  std::future<ImageF> image;
  if (input.image_bytes)
    image = std::async(std::launch::async,
                       [&] { return scalar_image_from_bytes(*input.image_bytes, "image", max_bytes); });
  d.labels = label_image_from_bytes(input.labels_bytes, "labels", max_bytes);
  if (image.valid()) {
    d.image = image.get();
    if (!d.image->grid.same_geometry(d.labels.grid))
      throw InputError("image: grid differs from the labels' grid (dims or world_from_voxel)");
  }
  d.read_seconds = seconds_since(t0);
  return d;
}

Message ServerCore::on_scan_push(const Message& m) {
  ScanPushRequest req = parse_scan_push_request(m);
  const std::string rid = m.request_id();
  std::string preop_id;
  {
    std::lock_guard lock(mutex_);
    preop_id = !loading_preop_id_.empty() ? loading_preop_id_ : ready_preop_id_;
  }
  if (preop_id.empty())
    return make_error_reply(rid, ErrorCode::kNotReady, "no preop is loaded: send preop.load first");

  ScanInput input{req.labels.bytes, req.image ? std::optional<std::string>(req.image->bytes) : std::nullopt};
  const std::string digest = content_digest(input);
  if (req.client_scan_id) {
    if (auto seen = store_.find_by_client_id(*req.client_scan_id)) {
      if (seen->digest != digest)
        return make_error_reply(rid, ErrorCode::kConflict,
                                "client_scan_id \"" + *req.client_scan_id + "\" was used for different data (" +
                                    seen->scan_id + ")");
      return make_scan_push_reply(rid, {seen->scan_id, true});
    }
  }
  // Checked before storing: a refused scan is never acknowledged nor kept.
  if (!queue_.has_room())
    return make_error_reply(rid, ErrorCode::kBusy,
                            "scan queue full (" + std::to_string(queue_.capacity()) + " waiting); retry later");
  auto decoded = std::make_shared<DecodedScan>(decode_scan(input));

  ScanRecord record;
  try {
    record = store_.add_scan(input, req.client_scan_id, digest, preop_id);
  } catch (const StoreWriteError& e) {
    spdlog::error("could not store a pushed scan: {}", e.what());
    return make_error_reply(rid, ErrorCode::kInternal,
                            std::string("the scan was NOT stored and is not queued (the store refused the write: ") +
                                e.what() + "); push it again once the store has space");
  } catch (const std::exception& e) {
    spdlog::error("could not store a pushed scan: {}", e.what());
    return make_error_reply(rid, ErrorCode::kInternal, std::string("the scan could not be stored: ") + e.what());
  }
  std::vector<std::string> retry;
  {
    std::lock_guard lock(mutex_);
    decoded_[record.scan_id] = decoded;
    retry.swap(unstored_results_);
  }
  // The store takes writes again: results it refused earlier are computed again first.
  for (const auto& id : retry) {
    spdlog::info("scan {}: the store takes writes again; processing it again", id);
    store_.mark_queued(id);
    queue_.restore(id);
  }
  if (!queue_.offer(record.scan_id)) queue_.restore(record.scan_id);  // stored: it must run
  spdlog::info("scan {} stored and queued (client id {})", record.scan_id,
               record.client_scan_id.value_or("-"));
  return make_scan_push_reply(rid, {record.scan_id, false});
}

Message ServerCore::on_scan_result(const Message& m) {
  ScanResultRequest req = parse_scan_result_request(m);
  const std::string rid = m.request_id();
  const auto record = store_.find(req.scan_id);
  if (!record) return make_error_reply(rid, ErrorCode::kNotFound, "no scan \"" + req.scan_id + "\"");
  if (record->state == StoredScanState::failed)
    return make_error_reply(rid, ErrorCode::kScanFailed,
                            req.scan_id + " failed in stage " + record->error_stage + ": " + record->error_message);
  if (record->state != StoredScanState::done)
    return make_error_reply(rid, ErrorCode::kNotReady, req.scan_id + " is not processed yet");
  bool deferred_pending = false;
  {
    std::lock_guard lock(mutex_);
    deferred_pending = deferred_pending_.count(req.scan_id) > 0;
  }
  ScanResultReply reply = collect_result_frames(store_, req, *record, deferred_pending);
  return make_scan_result_reply(rid, reply);
}

Message ServerCore::on_scan_list(const Message& m) {
  ScanListRequest req = parse_scan_list_request(m);
  std::optional<std::string> running, stage;
  {
    std::lock_guard lock(mutex_);
    running = current_scan_;
    stage = current_stage_;
  }
  ScanListReply reply;
  for (const auto& r : store_.list_newest_first(req.limit)) {
    ScanSummary s;
    s.scan_id = r.scan_id;
    s.client_scan_id = r.client_scan_id;
    s.received_at = r.received_at;
    s.finished_at = r.finished_at;
    if (r.state == StoredScanState::done) s.state = ScanState::kDone;
    else if (r.state == StoredScanState::failed) {
      s.state = ScanState::kFailed;
      s.error = ErrorInfo{error_code_from_string(r.error_code).value_or(ErrorCode::kScanFailed),
                          r.error_message};
    } else if (running && *running == r.scan_id) {
      s.state = ScanState::kProcessing;
      s.stage = stage;
    }
    reply.scans.push_back(std::move(s));
  }
  return make_scan_list_reply(m.request_id(), reply);
}

Message ServerCore::on_shutdown(const Message& m) {
  // The role was checked in handle(): an admin key, or no CURVE with
  // allow_unauthenticated_shutdown.
  ShutdownRequest req = parse_shutdown_request(m);
  spdlog::info("shutdown requested{}{}", req.reason.empty() ? "" : ": ", req.reason);
  shutdown_ = true;
  request_stop();
  return make_shutdown_reply(m.request_id());
}

// ---------------------------------------------------------------- engine side

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

void ServerCore::start() {
  {
    std::lock_guard lock(mutex_);
    ranks_ = engine_.ranks();
  }
  auto job = std::make_unique<PreopJob>();
  if (store_.has_preop()) {
    PreopRecord p = store_.load_preop();
    job->preop_id = p.preop_id;
    job->source = "store";
    job->label_table_json = p.label_table_json;
    job->stored_mesh = store_.load_mesh(p.preop_id);
    job->images = PreopImages{std::move(p.t1), std::move(p.labels)};
    spdlog::info("store holds preop {} ({} mesh); warming up from it", job->preop_id,
                 job->stored_mesh ? "with its" : "without a");
  } else if (settings_.preop.kind == DefaultPreop::Kind::atlas) {
    job->preop_id = new_preop_id();
    job->source = "atlas";
  } else if (settings_.preop.kind == DefaultPreop::Kind::files) {
    job->preop_id = new_preop_id();
    job->source = "files";
  } else {
    job.reset();
  }
  for (const auto& r : store_.queued_oldest_first()) {
    spdlog::info("re-queueing acknowledged scan {} (no result yet)", r.scan_id);
    queue_.restore(r.scan_id);
  }
  find_incomplete_results();
  std::lock_guard lock(mutex_);
  if (job) {
    loading_preop_id_ = job->preop_id;
    state_ = ServerState::kLoadingPreop;
    progress_ = Progress{"queued", 0.0};
    pending_preop_ = std::move(job);
  }
}

// The deferred outputs (metrics.json, field.h5, report.png) are stored after
// the result; a daemon killed in between leaves a done scan without some of
// them. field.h5 is the stored field.nii re-encoded, so it is made again here,
// exactly. metrics.json and report.png need the registration's images: the
// scan is registered again from its stored input (repair_scan) and only the
// missing files are added; result.h5 is never touched.
void ServerCore::find_incomplete_results() {
  for (const auto& r : store_.list_newest_first(std::numeric_limits<std::size_t>::max())) {
    if (r.state != StoredScanState::done) continue;
    const auto names = store_.result_file_names(r.scan_id);
    auto has = [&](const char* n) { return std::find(names.begin(), names.end(), n) != names.end(); };
    if (!has("field.h5") && has("field.nii")) {
      try {
        const auto h5 = engine_.itk_field_from_nifti(store_.read_result_file(r.scan_id, "field.nii").value());
        if (h5) {
          store_.add_result_file(r.scan_id, "field.h5", *h5);
          spdlog::warn("scan {}: field.h5 was missing (stopped before it was stored); made again from field.nii",
                       r.scan_id);
        }
      } catch (const std::exception& e) {
        spdlog::error("scan {}: field.h5 missing and could not be made again: {}", r.scan_id, e.what());
      }
    }
    if (!has("metrics.json") || (r.has_image && !has("report.png"))) {
      repairs_.push_back(r.scan_id);
      std::lock_guard lock(mutex_);
      deferred_pending_.insert(r.scan_id);  // pulls answer "pending" until the repair ends
    }
  }
}

void ServerCore::repair_scan(const std::string& scan_id) {
  const fs::path scratch = store_.dir() / "scans" / scan_id / "repair.tmp";
  try {
    const auto record = store_.find(scan_id);
    std::string preop_id;
    {
      std::lock_guard lock(mutex_);
      preop_id = ready_preop_id_;
    }
    if (!record || record->preop_id != preop_id)
      throw InputError("it was registered against another preop than the one loaded");
    const auto names = store_.result_file_names(scan_id);
    const DecodedScan d = decode_scan(store_.load_scan_input(scan_id));
    fs::create_directories(scratch);
    engine_.register_scan(d.labels, d.image, d.read_seconds, scratch, [](const std::string&, double, double) {});
    engine_.render_deferred(scan_id, [&](const std::string& name, const std::string& bytes) {
      if (std::find(names.begin(), names.end(), name) != names.end()) return;
      store_.add_result_file(scan_id, name, bytes);
      spdlog::warn("scan {}: {} was missing (stopped before it was stored); made again by registering the stored "
                   "scan again", scan_id, name);
    });
  } catch (const std::exception& e) {
    spdlog::error("scan {}: missing deferred outputs could not be made again: {}", scan_id, e.what());
  }
  std::error_code ec;
  fs::remove_all(scratch, ec);
  std::lock_guard lock(mutex_);
  deferred_pending_.erase(scan_id);
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

void ServerCore::run_preop_job(PreopJob job) {
  const auto t0 = Clock::now();
  const std::string id = job.preop_id;
  auto progress = [&](const std::string& stage, double fraction, double seconds) {
    const double whole = preop_fraction(stage, fraction);
    {
      std::lock_guard lock(mutex_);
      progress_ = Progress{stage, whole};
    }
    emit(make_event(PreopProgressEvent{id, stage, whole}));
    if (fraction >= 1.0) log_stage(StageTiming{StageScope::kPreop, "", id, stage, seconds, ""});
  };
  try {
    double atlas_seconds = 0.0;
    if (!job.images) {
      progress("atlas", 0.0, 0.0);
      const auto ta = Clock::now();
      if (job.source == "atlas") {
        job.images = engine_.load_default_atlas(settings_.atlas_cache_path());
      } else {
        PreopImages images{read_scalar_image(settings_.preop.t1), read_label_image(settings_.preop.labels)};
        std::optional<LabelTable> table;
        if (!settings_.preop.label_table.empty()) {
          job.label_table_json = read_text_file(settings_.preop.label_table);
          table = parse_label_table_json(job.label_table_json);
        }
        if (!images.t1.grid.same_geometry(images.labels.grid))
          throw InputError(settings_.preop.labels.string() + ": grid differs from the preop T1's");
        remap_preop_labels(images.labels, table ? &*table : nullptr);
        job.images = std::move(images);
      }
      atlas_seconds = seconds_since(ta);
      progress("atlas", 1.0, atlas_seconds);
    }
    const bool had_mesh = job.stored_mesh.has_value();
    engine_.load_preop(*job.images, std::move(job.stored_mesh), atlas_seconds, progress);
    const TetMesh& mesh = engine_.mesh();
    if (job.source != "store") {
      store_.save_preop(PreopRecord{id, job.source, job.images->t1, job.images->labels, job.label_table_json});
    }
    if (job.source != "store" || !had_mesh) store_.save_mesh(id, mesh);
    const MeshSize size{mesh.node_count(), mesh.tet_count()};
    const double seconds = seconds_since(t0);
    {
      std::lock_guard lock(mutex_);
      ready_preop_id_ = id;
      loading_preop_id_.clear();
      mesh_size_ = size;
      progress_.reset();
      last_error_.reset();
      state_ = ServerState::kReady;
    }
    spdlog::info("preop {} ready: {} nodes, {} tets, {:.2f} s", id, size.nodes, size.tets, seconds);
    emit(make_event(PreopReadyEvent{id, size, seconds}));
  } catch (const std::exception& e) {
    const bool input = dynamic_cast<const InputError*>(&e) != nullptr;
    const ErrorInfo error{input ? ErrorCode::kInvalidRequest : ErrorCode::kInternal,
                          std::string("preop ") + id + ": " + e.what()};
    spdlog::error("{}", error.message);
    {
      std::lock_guard lock(mutex_);
      loading_preop_id_.clear();
      last_error_ = error;
      state_ = engine_.ready() ? ServerState::kReady : ServerState::kIdle;
      progress_.reset();
    }
    emit(make_event(PreopFailedEvent{id, error}));
  }
}

void ServerCore::fail_scan(const ScanRecord& record, ErrorCode code, const std::string& message,
                           const std::string& stage) {
  spdlog::error("scan {} failed in {}: {}", record.scan_id, stage, message);
  try {
    store_.save_failure(record.scan_id, std::string(to_string(code)), message, stage);
  } catch (const std::exception& e) {
    // Shown now; the store still holds the scan without a result, so a
    // restart processes it again.
    spdlog::error("scan {}: the failure could not be stored: {}", record.scan_id, e.what());
    store_.mark_failed_unstored(record.scan_id, std::string(to_string(code)), message, stage);
  }
  emit(make_event(ScanFailedEvent{record.scan_id, record.client_scan_id, stage, ErrorInfo{code, message}}));
}

// The result was computed but the store refused it (disk full, file-size
// limit): the scan is reported failed for now and computed again after the
// next successful write to the store (a push) or at the next start.
void ServerCore::result_not_stored(const ScanRecord& record, const std::string& why) {
  const std::string message = "the result could not be stored (" + why +
                              "); the scan is kept and processed again once the store takes writes";
  spdlog::error("scan {}: {}", record.scan_id, message);
  store_.mark_failed_unstored(record.scan_id, std::string(to_string(ErrorCode::kInternal)), message, "store");
  {
    std::lock_guard lock(mutex_);
    unstored_results_.push_back(record.scan_id);
  }
  emit(make_event(ScanFailedEvent{record.scan_id, record.client_scan_id, "store", ErrorInfo{ErrorCode::kInternal, message}}));
}

// metrics.json (label overlap figures that judge the result), field.h5
// (field.nii again, in ITK's encoding) and report.png (a picture for the
// record) are made after the scan was announced, so they never delay the
// field; each is stored durably as soon as it is ready. A failure is logged
// and never fails the scan. Meanwhile the socket thread answers pulls of them
// with a "pending" unavailable entry.
void ServerCore::add_deferred_outputs(const std::string& scan_id, const std::string& preop_id) {
  auto t0 = Clock::now();
  try {
    engine_.render_deferred(scan_id, [&](const std::string& name, const std::string& bytes) {
      store_.add_result_file(scan_id, name, bytes);
      const std::string stage = name == "report.png"     ? "report"
                                : name == "field.h5"     ? "itk_field"
                                : name == "metrics.json" ? "metrics"
                                                         : "deferred";
      log_stage(StageTiming{StageScope::kIntraop, scan_id, preop_id, stage, seconds_since(t0), ""});
      t0 = Clock::now();
    });
  } catch (const std::exception& e) {
    spdlog::error("scan {}: deferred outputs (metrics.json, field.h5, report.png) incomplete: {}", scan_id, e.what());
  }
  std::lock_guard lock(mutex_);
  deferred_pending_.erase(scan_id);
}

void ServerCore::run_scan(const std::string& scan_id) {
  const auto t0 = Clock::now();
  const auto record = store_.find(scan_id);
  if (!record) return;
  std::string preop_id;
  std::shared_ptr<DecodedScan> decoded;
  {
    std::lock_guard lock(mutex_);
    preop_id = ready_preop_id_;
    state_ = ServerState::kProcessing;
    current_scan_ = scan_id;
    current_stage_ = "decode";
    if (auto it = decoded_.find(scan_id); it != decoded_.end()) {
      decoded = it->second;
      decoded_.erase(it);
    }
  }
  std::string stage = "decode";
  auto progress = [&](const std::string& s, double fraction, double seconds) {
    stage = s;
    {
      std::lock_guard lock(mutex_);
      current_stage_ = s;
    }
    emit(make_event(ScanProgressEvent{scan_id, s, std::clamp(fraction, 0.0, 1.0)}));
    if (fraction >= 1.0) log_stage(StageTiming{StageScope::kIntraop, scan_id, preop_id, s, seconds, ""});
  };
  const fs::path scratch = store_.dir() / "scans" / scan_id / "work.tmp";
  try {
    if (record->preop_id != preop_id)
      throw InputError("pushed against preop " + record->preop_id + " but " + preop_id + " is loaded");
    if (!decoded) decoded = std::make_shared<DecodedScan>(decode_scan(store_.load_scan_input(scan_id)));
    // "decode" (the pushed bytes to images) is the daemon's; the engine logs its own "read".
    progress("decode", 1.0, decoded->read_seconds);
    fs::remove_all(scratch);
    fs::create_directories(scratch);
    EngineScanOutput out = engine_.register_scan(decoded->labels, decoded->image, decoded->read_seconds, scratch, progress);
    const auto t_store = Clock::now();
    stage = "store";
    {
      // Marked before the result becomes visible: a pull in between must see
      // the deferred parts as pending, not as missing for good (the soak
      // caught one such pull at np 2).
      std::lock_guard lock(mutex_);
      deferred_pending_.insert(scan_id);
    }
    try {
      store_.save_result(scan_id, out.files, out.kind, out.fallback_reason);
    } catch (...) {
      std::lock_guard lock(mutex_);
      deferred_pending_.erase(scan_id);
      throw;
    }
    progress("store", 1.0, seconds_since(t_store));
    fs::remove_all(scratch);
    const double seconds = seconds_since(t0);
    spdlog::info("scan {} done ({}) in {:.3f} s", scan_id, out.kind, seconds);
    emit(make_event(ScanDoneEvent{scan_id, record->client_scan_id, seconds}));
    add_deferred_outputs(scan_id, preop_id);
  } catch (const StoreWriteError& e) {
    result_not_stored(*record, e.what());
  } catch (const InputError& e) {
    fail_scan(*record, ErrorCode::kInvalidRequest, e.what(), stage);
  } catch (const ComputeError& e) {
    fail_scan(*record, ErrorCode::kScanFailed, e.what(), stage);
  } catch (const std::exception& e) {
    fail_scan(*record, ErrorCode::kInternal, e.what(), stage);
  }
  std::error_code ec;
  fs::remove_all(scratch, ec);
  std::lock_guard lock(mutex_);
  state_ = loading_preop_id_.empty() ? ServerState::kReady : ServerState::kLoadingPreop;
  current_scan_.reset();
  current_stage_.reset();
}

}  // namespace brainshift::server
