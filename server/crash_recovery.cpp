// ServerCore's crash recovery, on the engine thread at start-up: the warm
// state from the store, acknowledged scans without a result re-queued, done
// scans missing deferred outputs repaired.
#include <algorithm>
#include <limits>

#include <spdlog/spdlog.h>

#include "core/errors.h"
#include "protocol/result_outputs.h"
#include "server/label_mapping.h"
#include "server/server_core_internal.h"

namespace brainshift::server {
namespace fs = std::filesystem;
using namespace protocol;

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
    job->patient_id = p.patient_id;
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
    job->patient_id = settings_.preop.patient_id;
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
    loading_patient_id_ = job->patient_id;
    state_ = ServerState::kLoadingPreop;
    progress_ = Progress{"queued", 0.0};
    pending_preop_ = std::move(job);
  }
}

namespace {

// The stored name of a part the result has, if any.
std::optional<std::string> stored_name(ResultPart part, const std::vector<std::string>& names) {
  for (const auto& n : stored_file_names(part))
    if (std::find(names.begin(), names.end(), n) != names.end()) return n;
  return std::nullopt;
}

}  // namespace

// The deferred parts (result_outputs.h) are stored after the result; a
// daemon killed in between leaves a done scan without some of them. One that
// re-encodes a stored part (field.h5: field.nii in ITK's encoding) is made
// again from it here, exactly (remake_part). The others need the
// registration's images: the scan is registered again from its stored input
// (repair_scan) and only the missing files are added; result.h5 is never
// touched. Which parts a scan should have is its rows' presence (report.png
// only with an intraop image).
void ServerCore::find_incomplete_results() {
  for (const auto& r : store_.list_newest_first(std::numeric_limits<std::size_t>::max())) {
    if (r.state != StoredScanState::done) continue;
    const auto names = store_.result_file_names(r.scan_id);
    bool register_again = false;
    for (const auto& row : kResultOutputs) {
      if (!row.deferred || !part_expected(row.part, scan_facts(r)) || stored_name(row.part, names)) continue;
      if (!row.remade_from) {
        register_again = true;
      } else if (const auto source = stored_name(*row.remade_from, names)) {
        remake_part(r.scan_id, row.part, *source);
      }
    }
    if (register_again) {
      repairs_.push_back(r.scan_id);
      std::lock_guard lock(mutex_);
      deferred_pending_.insert(r.scan_id);  // pulls answer "pending" until the repair ends
    }
  }
}

void ServerCore::remake_part(const std::string& scan_id, ResultPart part, const std::string& source) {
  const std::string name(result_output(part).stored);
  try {
    std::optional<std::string> bytes;
    if (part == ResultPart::kDisplacementItk)
      bytes = engine_.itk_field_from_nifti(store_.read_result_file(scan_id, source).value());
    if (!bytes) throw std::runtime_error("the engine cannot make it from " + source);
    store_.add_result_file(scan_id, name, *bytes);
    spdlog::warn("scan {}: {} was missing (stopped before it was stored); made again from {}", scan_id, name, source);
  } catch (const std::exception& e) {
    spdlog::error("scan {}: {} missing and could not be made again: {}", scan_id, name, e.what());
  }
}

void ServerCore::repair_scan(const std::string& scan_id) {
  try {
    const auto record = store_.find(scan_id);
    std::string preop_id;
    std::shared_ptr<const protocol::LabelMap> label_map;
    {
      std::lock_guard lock(mutex_);
      preop_id = ready_preop_id_;
      label_map = ready_label_map_;
    }
    if (!record || record->preop_id != preop_id)
      throw InputError("it was registered against another preop than the one loaded");
    const auto names = store_.result_file_names(scan_id);
    DecodedScan d = decode_scan(store_.load_scan_input(scan_id));
    if (label_map && d.labels) map_label_values(*d.labels, label_map.get(), engine_.label_table());
    engine_.register_scan(d.labels, d.image, d.labels_use, d.read_seconds, [](const std::string&, double, double) {});
    engine_.render_deferred(scan_id, [&](const std::string& name, const std::string& bytes) {
      if (std::find(names.begin(), names.end(), name) != names.end()) return;
      store_.add_result_file(scan_id, name, bytes);
      spdlog::warn("scan {}: {} was missing (stopped before it was stored); made again by registering the stored "
                   "scan again", scan_id, name);
    });
  } catch (const std::exception& e) {
    spdlog::error("scan {}: missing deferred outputs could not be made again: {}", scan_id, e.what());
  }
  std::lock_guard lock(mutex_);
  deferred_pending_.erase(scan_id);
}

}  // namespace brainshift::server
