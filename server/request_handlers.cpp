// ServerCore's socket side: decoding, the role check and one handler per
// request type. Runs on the socket thread; never waits for the engine.
#include <algorithm>
#include <functional>

#include <spdlog/spdlog.h>

#include "core/errors.h"
#include "image/label_placement.h"
#include "image/nifti_io.h"
#include "protocol/media.h"
#include "server/label_mapping.h"
#include "protocol/result_outputs.h"
#include "server/server_core_internal.h"

namespace brainshift::server {
namespace fs = std::filesystem;
using namespace protocol;

namespace {

// Frames of the requested parts of a done scan, with every missing part in
// `unavailable` (e.g. no warped_image when the engine wrote none).
// deferred_pending: the deferred parts (result_outputs.h) are still being
// made (they follow scan.done, see ServerCore::add_deferred_outputs).
// read_file: a result file's bytes by name, nullopt when absent (from the
// store, or from memory while the result is not yet written); file_names:
// every file the result has (its models are those under models/). Asked for
// no structure in particular, the models are those of every structure of the
// label table that has one (a missing one is named unavailable), then any
// other the result holds (made under another label table).
using ResultFileReader = std::function<std::optional<std::string>(const std::string& name)>;
std::vector<std::string> structures_to_send(const std::vector<std::string>& asked, const brainshift::LabelTable& table,
                                            const std::vector<std::string>& file_names) {
  if (!asked.empty()) return asked;
  std::vector<std::string> out;
  for (const auto& e : table.entries)
    if (e.make_model) out.push_back(e.name);
  for (const auto& name : file_names)
    if (auto s = structure_of_model_file(name); s && std::find(out.begin(), out.end(), *s) == out.end())
      out.push_back(*s);
  return out;
}

ScanResultReply collect_result_frames(const ResultFileReader& read_file, const std::vector<std::string>& file_names,
                                      const brainshift::LabelTable& table, const ScanResultRequest& request,
                                      const ScanRecord& record, bool deferred_pending) {
  ScanResultReply reply;
  reply.scan_id = request.scan_id;
  reply.result = record.result;
  auto add = [&](const std::string& frame, const std::vector<std::string>& files, const char* why_missing) {
    for (const auto& file : files) {
      auto bytes = read_file(file);
      if (!bytes) continue;
      const std::string media = result_media_type(file, *bytes);
      reply.frames.push_back(Frame{frame, media, std::move(*bytes)});
      return true;
    }
    reply.unavailable.push_back({frame, why_missing});
    return false;
  };
  for (ResultPart part : request.parts) {
    if (part == ResultPart::kModels) {
      for (const auto& s : structures_to_send(request.structures, table, file_names))
        add(model_frame_name(s), {model_file_name(s)}, "no model of this structure (label absent from the preop)");
      continue;
    }
    // Why a part is missing, from its row (result_outputs.h).
    const ResultOutput& row = result_output(part);
    const std::string_view not_expected = why_not_expected(part, scan_facts(record));
    const bool pending = not_expected.empty() && row.deferred && deferred_pending;
    const std::string why =
        !not_expected.empty() ? std::string(not_expected)
        : pending             ? "made just after the answer; ask again shortly"
        : row.deferred        ? std::string(row.stored) + " was not made (see the server log)"
        : row.presence == PartPresence::kEngineSegmentation
            ? "the pushed labels were used as given: their refinement by the image was refused or is off "
              "(metrics.given_labels says which)"
            : "not in this result";
    if (!add(frame_name(part), stored_file_names(part), why.c_str()) && pending) reply.unavailable.back().pending = true;
  }
  return reply;
}

}  // namespace

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
      case MessageType::kLabelsGet:
        parse_labels_request(m);
        return make_labels_reply(m.request_id(), served_labels(engine_.label_table()));
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

Message ServerCore::on_status(const Message& m) {
  parse_status_request(m);
  StatusReply r = status();
  if (status_extension_) status_extension_(r);  // outside mutex_
  return make_status_reply(m.request_id(), r);
}

Message ServerCore::on_preop_load(const Message& m) {
  PreopLoadRequest req = parse_preop_load_request(m);  // parses the label map once
  auto job = std::make_unique<PreopJob>();
  if (req.use_default_atlas) {
    job->source = "atlas";
  } else {
    const std::size_t max_bytes = engine_.max_image_bytes();
    PreopImages images;
    images.t1 = scalar_image_from_bytes(req.t1->bytes, "t1", max_bytes);
    images.labels = label_image_from_bytes(req.labels->bytes, "labels", max_bytes);
    images.labels = labels_on_image_grid(std::move(images.labels), images.t1.grid, "labels");
    if (req.label_map) {
      job->label_map = std::make_shared<const protocol::LabelMap>(std::move(*req.label_map));
      job->label_table_json = req.label_table->bytes;
    }
    map_label_values(images.labels, job->label_map.get(), engine_.label_table());
    job->images = std::move(images);
    job->source = "upload";
  }
  std::lock_guard lock(mutex_);
  if (state_ == ServerState::kLoadingPreop || state_ == ServerState::kProcessing || pending_preop_ ||
      queue_.size() > 0)
    return make_error_reply(m.request_id(), ErrorCode::kBusy,
                            "a preop warm-up or scans are in progress; retry when the server is ready or idle");
  job->preop_id = new_preop_id();
  job->patient_id = req.patient_id;
  const std::string id = job->preop_id;
  loading_preop_id_ = id;
  loading_patient_id_ = req.patient_id;
  state_ = ServerState::kLoadingPreop;
  progress_ = Progress{"queued", 0.0};
  pending_preop_ = std::move(job);
  // The identifier itself stays out of the log (it identifies a person).
  spdlog::info("preop.load accepted: {} ({}, {})", id, pending_preop_->source,
               req.patient_id ? "patient named" : "no patient named");
  return make_preop_load_reply(m.request_id(), {id});
}

Message ServerCore::on_scan_push(const Message& m) {
  ScanPushRequest req = parse_scan_push_request(m);
  const std::string rid = m.request_id();
  std::string preop_id;
  std::optional<std::string> preop_patient;
  {
    std::lock_guard lock(mutex_);
    const bool loading = !loading_preop_id_.empty();
    preop_id = loading ? loading_preop_id_ : ready_preop_id_;
    preop_patient = loading ? loading_patient_id_ : ready_patient_id_;
  }
  if (preop_id.empty())
    return make_error_reply(rid, ErrorCode::kNotReady, "no preop is loaded: send preop.load first");
  // A scan of another patient is never registered to this preop, nor kept
  // (checked before the idempotence key: it is not this case's scan).
  if (req.patient_id && preop_patient && *req.patient_id != *preop_patient) {
    spdlog::warn("scan.push {} refused: it names another patient than preop {} (not stored)", rid, preop_id);
    return make_error_reply(rid, ErrorCode::kInvalidRequest,
                            "the scan is of patient \"" + *req.patient_id + "\" and the loaded preop " + preop_id +
                                " of patient \"" + *preop_patient +
                                "\": a scan of another patient is not registered; it was NOT stored");
  }

  PushedScan input{req.labels ? std::optional<std::string>(req.labels->bytes) : std::nullopt,
                   req.image ? std::optional<std::string>(req.image->bytes) : std::nullopt, req.labels_use};
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
  std::shared_ptr<const UnwrittenResult> unwritten;
  bool deferred_pending = false;
  {
    std::lock_guard lock(mutex_);
    if (auto it = unwritten_results_.find(req.scan_id); it != unwritten_results_.end()) unwritten = it->second;
    deferred_pending = deferred_pending_.count(req.scan_id) > 0;
  }
  if (unwritten) {
    const auto& files = unwritten->files;
    const ResultFileReader from_memory = [&files](const std::string& name) -> std::optional<std::string> {
      const auto it = files.find(name);
      return it == files.end() ? std::nullopt : std::optional<std::string>(it->second);
    };
    std::vector<std::string> names;
    for (const auto& [name, bytes] : files) names.push_back(name);
    return make_scan_result_reply(rid,
                                  collect_result_frames(from_memory, names, engine_.label_table(), req, unwritten->record, deferred_pending));
  }
  // Looked up after the unwritten results: a result leaves them only once the store has it.
  const auto record = store_.find(req.scan_id);
  if (!record) return make_error_reply(rid, ErrorCode::kNotFound, "no scan \"" + req.scan_id + "\"");
  if (record->state == StoredScanState::failed)
    return make_error_reply(rid, ErrorCode::kScanFailed,
                            req.scan_id + " failed in stage " + record->error_stage + ": " + record->error_message);
  if (record->state != StoredScanState::done)
    return make_error_reply(rid, ErrorCode::kNotReady, req.scan_id + " is not processed yet");
  {
    std::lock_guard lock(mutex_);
    deferred_pending = deferred_pending_.count(req.scan_id) > 0;
  }
  const ResultFileReader from_store = [&](const std::string& name) {
    return store_.read_result_file(req.scan_id, name);
  };
  ScanResultReply reply =
      collect_result_frames(from_store, store_.result_file_names(req.scan_id), engine_.label_table(), req, *record, deferred_pending);
  return make_scan_result_reply(rid, reply);
}

Message ServerCore::on_scan_list(const Message& m) {
  ScanListRequest req = parse_scan_list_request(m);
  std::optional<std::string> running, stage;
  std::map<std::string, std::shared_ptr<const UnwrittenResult>> unwritten;
  {
    std::lock_guard lock(mutex_);
    running = current_scan_;
    stage = current_stage_;
    unwritten = unwritten_results_;
  }
  ScanListReply reply;
  for (const auto& stored : store_.list_newest_first(req.limit)) {
    const auto it = unwritten.find(stored.scan_id);
    const ScanRecord& r = it != unwritten.end() ? it->second->record : stored;
    ScanSummary s;
    s.scan_id = r.scan_id;
    s.client_scan_id = r.client_scan_id;
    s.received_at = r.received_at;
    s.finished_at = r.finished_at;
    if (r.state == StoredScanState::done) {
      s.state = ScanState::kDone;
      s.result = r.result;
    } else if (r.state == StoredScanState::failed) {
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

}  // namespace brainshift::server
