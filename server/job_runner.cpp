// ServerCore's job runner on the engine thread: a preop warm-up, a scan
// (register, store, announce) and the deferred outputs after it.
#include <algorithm>

#include <spdlog/spdlog.h>

#include "core/errors.h"
#include "core/file_bytes.h"
#include "image/label_placement.h"
#include "image/nifti_io.h"
#include "protocol/events.h"
#include "protocol/result_outputs.h"
#include "protocol/stage_names.h"
#include "server/label_mapping.h"
#include "server/server_core_internal.h"

namespace brainshift::server {
namespace fs = std::filesystem;
using namespace protocol;

namespace {

// Share of the whole warm-up each preop stage takes (measured on the default
// atlas: meshing and factorisation dominate); only for the progress bar.
double preop_fraction(const std::string& stage, double stage_fraction) {
  static const std::vector<std::pair<std::string_view, double>> weights = {{stages::kAtlas, 0.05},
                                                                           {stages::kMesh, 0.45},
                                                                           {stages::kAssemble, 0.10},
                                                                           {stages::kFactorise, 0.35},
                                                                           {stages::kPreopModels, 0.05}};
  double before = 0.0;
  for (const auto& [name, w] : weights) {
    if (name == stage) return std::min(1.0, before + w * stage_fraction);
    before += w;
  }
  return before;  // unknown stage: report what is known to be done
}

}  // namespace

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
    // A stored preop's map is parsed here, once (an upload's by the codec).
    if (!job.label_map && !job.label_table_json.empty())
      job.label_map = std::make_shared<const protocol::LabelMap>(parse_label_map_json(job.label_table_json));
    double atlas_seconds = 0.0;
    if (!job.images) {
      progress(std::string(stages::kAtlas), 0.0, 0.0);
      const auto ta = Clock::now();
      if (job.source == "atlas") {
        job.images = engine_.load_default_atlas(settings_.atlas_cache_path());
      } else {
        PreopImages images{read_scalar_image(settings_.preop.t1), read_label_image(settings_.preop.labels)};
        if (!settings_.preop.label_table.empty()) {
          job.label_table_json = read_whole_file(settings_.preop.label_table, "label map");
          job.label_map = std::make_shared<const protocol::LabelMap>(parse_label_map_json(job.label_table_json));
        }
        images.labels = labels_on_image_grid(std::move(images.labels), images.t1.grid, settings_.preop.labels.string());
        map_label_values(images.labels, job.label_map.get(), engine_.label_table());
        job.images = std::move(images);
      }
      atlas_seconds = seconds_since(ta);
      progress(std::string(stages::kAtlas), 1.0, atlas_seconds);
    }
    const bool had_mesh = job.stored_mesh.has_value();
    engine_.load_preop(*job.images, std::move(job.stored_mesh), atlas_seconds, progress);
    const TetMesh& mesh = engine_.mesh();
    if (job.source != "store") {
      store_.save_preop(
          PreopRecord{id, job.source, job.images->t1, job.images->labels, job.label_table_json, job.patient_id});
    }
    if (job.source != "store" || !had_mesh) store_.save_mesh(id, mesh);
    const MeshSize size{mesh.node_count(), mesh.tet_count()};
    const double seconds = seconds_since(t0);
    {
      std::lock_guard lock(mutex_);
      ready_preop_id_ = id;
      ready_patient_id_ = job.patient_id;
      loading_patient_id_.reset();
      ready_label_map_ = std::move(job.label_map);
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
      loading_patient_id_.reset();
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
  const std::string stage(stages::kStore);
  store_.mark_failed_unstored(record.scan_id, std::string(to_string(ErrorCode::kInternal)), message, stage);
  {
    std::lock_guard lock(mutex_);
    unstored_results_.push_back(record.scan_id);
  }
  emit(make_event(ScanFailedEvent{record.scan_id, record.client_scan_id, stage, ErrorInfo{ErrorCode::kInternal, message}}));
}

// The deferred parts (result_outputs.h: metrics.json, the label overlap
// figures that judge the result; field.h5, field.nii again in ITK's
// encoding; report.png, a picture for the record) are made after the scan
// was announced, so they never delay the field; each is stored durably as
// soon as it is ready and timed as its row's stage. A failure is logged and
// never fails the scan. Meanwhile the socket thread answers pulls of them
// with a "pending" unavailable entry.
void ServerCore::add_deferred_outputs(const std::string& scan_id, const std::string& preop_id) {
  auto t0 = Clock::now();
  try {
    engine_.render_deferred(scan_id, [&](const std::string& name, const std::string& bytes) {
      store_.add_result_file(scan_id, name, bytes);
      const auto part = part_of_file(name);
      const std::string_view stage = part ? result_output(*part).deferred_stage : "";
      if (stage.empty()) spdlog::error("scan {}: {} came after the answer but is no deferred part", scan_id, name);
      else log_stage(StageTiming{StageScope::kIntraop, scan_id, preop_id, std::string(stage), seconds_since(t0), ""});
      t0 = Clock::now();
    });
  } catch (const std::exception& e) {
    spdlog::error("scan {}: deferred outputs incomplete: {}", scan_id, e.what());
  }
  {
    std::lock_guard lock(mutex_);
    deferred_pending_.erase(scan_id);
  }
  if (deferred_stored_) deferred_stored_(scan_id);
}

// The store's fsync of ~90 MB (0.1-0.3 s) is off the latency path: the
// result is announced and served from memory first. It is derived from the
// scan, which is durable since its acknowledgement, so a crash before the
// write loses nothing: the restart finds the scan without a result and
// computes it again.
std::shared_ptr<const ServerCore::UnwrittenResult> ServerCore::publish_result(const ScanRecord& record,
                                                                              EngineScanOutput out, double seconds) {
  auto result = std::make_shared<UnwrittenResult>();
  result->record = record;
  result->record.state = StoredScanState::done;
  result->record.finished_at = utc_now();
  result->record.result = out.result;
  result->files = std::move(out.files);
  {
    std::lock_guard lock(mutex_);
    unwritten_results_[record.scan_id] = result;
  }
  spdlog::info("scan {} done ({}) in {:.3f} s", record.scan_id, to_string(out.result.kind), seconds);
  emit(make_event(ScanDoneEvent{record.scan_id, record.client_scan_id, seconds, out.result}));
  return result;
}

bool ServerCore::write_result(const UnwrittenResult& result, const std::string& preop_id) {
  const ScanRecord& r = result.record;
  const auto t0 = Clock::now();
  try {
    store_.save_result(r.scan_id, result.files, r.result, r.finished_at.value_or(""));
  } catch (const std::exception& e) {  // StoreWriteError, or a result that did not read back
    {
      std::lock_guard lock(mutex_);
      unwritten_results_.erase(r.scan_id);
      deferred_pending_.erase(r.scan_id);
    }
    result_not_stored(r, e.what());
    return false;
  }
  {
    std::lock_guard lock(mutex_);
    unwritten_results_.erase(r.scan_id);  // the store serves it from now on
  }
  log_stage(StageTiming{StageScope::kIntraop, r.scan_id, preop_id, std::string(stages::kStore), seconds_since(t0), ""});
  if (result_stored_) result_stored_(r.scan_id);
  return true;
}

void ServerCore::run_scan(const std::string& scan_id) {
  const auto t0 = Clock::now();
  const auto record = store_.find(scan_id);
  if (!record) return;
  std::string preop_id;
  std::shared_ptr<DecodedScan> decoded;
  std::shared_ptr<const protocol::LabelMap> label_map;
  {
    std::lock_guard lock(mutex_);
    preop_id = ready_preop_id_;
    label_map = ready_label_map_;
    state_ = ServerState::kProcessing;
    current_scan_ = scan_id;
    current_stage_ = std::string(stages::kDecode);
    if (auto it = decoded_.find(scan_id); it != decoded_.end()) {
      decoded = it->second;
      decoded_.erase(it);
    }
  }
  std::string stage(stages::kDecode);
  auto progress = [&](const std::string& s, double fraction, double seconds) {
    stage = s;
    {
      std::lock_guard lock(mutex_);
      current_stage_ = s;
    }
    emit(make_event(ScanProgressEvent{scan_id, s, std::clamp(fraction, 0.0, 1.0)}));
    if (fraction >= 1.0) log_stage(StageTiming{StageScope::kIntraop, scan_id, preop_id, s, seconds, ""});
  };
  try {
    if (record->preop_id != preop_id)
      throw InputError("pushed against preop " + record->preop_id + " but " + preop_id + " is loaded");
    if (!decoded) decoded = std::make_shared<DecodedScan>(decode_scan(store_.load_scan_input(scan_id)));
    if (label_map && decoded->labels) map_label_values(*decoded->labels, label_map.get(), engine_.label_table());
    // "decode" (the pushed bytes to images) is the daemon's; the engine logs its own "read".
    progress(std::string(stages::kDecode), 1.0, decoded->read_seconds);
    EngineScanOutput out = engine_.register_scan(decoded->labels, decoded->image, decoded->labels_use, decoded->read_seconds, progress);
    {
      // Marked before the result becomes visible: a pull in between must see
      // the deferred parts as pending, not as missing for good (the soak
      // caught one such pull at np 2).
      std::lock_guard lock(mutex_);
      deferred_pending_.insert(scan_id);
    }
    const auto result = publish_result(*record, std::move(out), seconds_since(t0));
    if (result_write_fault_.fires(0)) {
      spdlog::warn("BRAINSHIFT_INJECT_FAULT: the result of scan {} is served from memory and never written",
                   scan_id);
    } else if (write_result(*result, preop_id)) {
      add_deferred_outputs(scan_id, preop_id);
    }
  } catch (const InputError& e) {
    fail_scan(*record, ErrorCode::kInvalidRequest, e.what(), stage);
  } catch (const ComputeError& e) {
    fail_scan(*record, ErrorCode::kScanFailed, e.what(), stage);
  } catch (const std::exception& e) {
    fail_scan(*record, ErrorCode::kInternal, e.what(), stage);
  }
  std::lock_guard lock(mutex_);
  state_ = loading_preop_id_.empty() ? ServerState::kReady : ServerState::kLoadingPreop;
  current_scan_.reset();
  current_stage_.reset();
}

}  // namespace brainshift::server
