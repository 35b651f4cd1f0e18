#include "protocol/requests.h"

#include <algorithm>
#include <array>
#include <set>
#include <utility>

#include "protocol/fields.h"
#include "protocol/media.h"
#include "protocol/message_parsing.h"
#include "protocol/version.h"

namespace brainshift::protocol {
namespace {

using nlohmann::json;
using detail::FieldReader;
using detail::context_of;
using detail::expect_frames;
using detail::expect_type;
using detail::with_request_id;

template <class E, std::size_t N>
using NameTable = std::array<std::pair<E, std::string_view>, N>;

constexpr NameTable<ServerState, 4> kServerStates{{{ServerState::kIdle, "idle"},
                                                   {ServerState::kLoadingPreop, "loading_preop"},
                                                   {ServerState::kReady, "ready"},
                                                   {ServerState::kProcessing, "processing"}}};
constexpr NameTable<ScanState, 4> kScanStates{{{ScanState::kQueued, "queued"},
                                               {ScanState::kProcessing, "processing"},
                                               {ScanState::kDone, "done"},
                                               {ScanState::kFailed, "failed"}}};
// "patient_id" of preop.load and scan.push, normalised (fields.h).
std::optional<std::string> patient_id_field(const FieldReader& f) {
  const std::optional<std::string> raw = f.opt_string("patient_id");
  if (!raw) return std::nullopt;
  std::optional<std::string> id = detail::normalised_patient_id(*raw);
  if (!id) f.fail("patient_id", std::string("must be ") + detail::kPatientIdRule);
  return id;
}

template <class E, std::size_t N>
std::string_view name_of(const NameTable<E, N>& table, E value) {
  for (const auto& [e, n] : table)
    if (e == value) return n;
  throw std::logic_error("enum value without a wire name");
}

template <class E, std::size_t N>
std::optional<E> value_of(const NameTable<E, N>& table, std::string_view name) {
  for (const auto& [e, n] : table)
    if (n == name) return e;
  return std::nullopt;
}

// A frame of that name, its media type accepted by `accepts`, content checked.
template <class Accepts>
std::optional<Frame> get_frame(const Message& m, std::string_view name, Accepts accepts) {
  const Frame* f = m.find_frame(name);
  if (!f) return std::nullopt;
  if (!accepts(f->media_type))
    throw ProtocolError(ErrorCode::kInvalidRequest,
                        context_of(m) + ": frame \"" + f->name + "\" may not have media type " +
                            f->media_type,
                        m.request_id());
  media::check_content(*f);
  return *f;
}

bool nifti_media(std::string_view t) { return media::is_nifti(t); }
bool json_media(std::string_view t) { return t == media::kJson; }

Message with_frames(Message m, std::vector<Frame> frames) {
  m.frames = std::move(frames);
  return m;
}

json string_array(const std::vector<std::string>& v) { return json(v); }

}  // namespace

// ---- enumerations ----------------------------------------------------------

std::string_view to_string(ServerState s) { return name_of(kServerStates, s); }
std::string_view to_string(ScanState s) { return name_of(kScanStates, s); }
std::optional<ServerState> server_state_from_string(std::string_view s) {
  return value_of(kServerStates, s);
}
std::optional<ScanState> scan_state_from_string(std::string_view s) {
  return value_of(kScanStates, s);
}
// ---- status ----------------------------------------------------------------

Message make_status_request(const std::string& request_id) {
  return make_message(MessageType::kStatus, request_id);
}

StatusRequest parse_status_request(const Message& m) {
  expect_type(m, MessageType::kStatus);
  expect_frames(m, {});
  return {};
}

Message make_status_reply(const std::string& request_id, const StatusReply& r) {
  Message m = make_message(MessageType::kStatusReply, request_id);
  auto& h = m.header;
  h["state"] = std::string(to_string(r.state));
  if (r.progress) h["progress"] = {{"stage", r.progress->stage}, {"fraction", r.progress->fraction}};
  h["versions"] = r.versions;
  h["versions"]["protocol"] = std::to_string(kProtocolVersion);
  if (r.preop_id) h["preop_id"] = *r.preop_id;
  if (r.preop_patient_id) h["preop_patient_id"] = *r.preop_patient_id;
  if (r.mesh) h["mesh"] = to_json_value(*r.mesh);
  h["mpi_ranks"] = r.mpi_ranks;
  h["queue"] = {{"depth", r.queue.depth}, {"capacity", r.queue.capacity}};
  if (r.current_scan_id) h["current_scan_id"] = *r.current_scan_id;
  if (r.last_error) h["last_error"] = to_json_value(*r.last_error);
  if (r.openigtlink)
    h["openigtlink"] = {{"port", r.openigtlink->port},
                        {"clients", r.openigtlink->clients},
                        {"messages_sent", r.openigtlink->messages_sent},
                        {"messages_dropped", r.openigtlink->messages_dropped}};
  return m;
}

StatusReply parse_status_reply(const Message& m) {
  expect_type(m, MessageType::kStatusReply);
  expect_frames(m, {});
  const FieldReader f(m.header, "status.reply");
  StatusReply r;
  const auto state = server_state_from_string(f.string("state"));
  if (!state) f.fail("state", "is not a known server state");
  r.state = *state;
  if (const json* p = f.opt_object("progress")) {
    const FieldReader pf(*p, "status.reply.progress");
    r.progress = Progress{pf.string("stage"), pf.fraction("fraction")};
  }
  for (const auto& [k, v] : f.object("versions").items()) {
    if (!v.is_string()) f.fail("versions", "values must be strings");
    r.versions[k] = v.get<std::string>();
  }
  r.preop_id = f.opt_string("preop_id");
  r.preop_patient_id = f.opt_string("preop_patient_id");
  if (const json* mesh = f.opt_object("mesh")) r.mesh = mesh_size_from_json(*mesh, "status.reply.mesh");
  r.mpi_ranks = f.uint("mpi_ranks");
  const FieldReader q(f.object("queue"), "status.reply.queue");
  r.queue = {q.uint("depth"), q.uint("capacity")};
  r.current_scan_id = f.opt_string("current_scan_id");
  if (const json* e = f.opt_object("last_error"))
    r.last_error = error_info_from_json(*e, "status.reply.last_error");
  if (const json* g = f.opt_object("openigtlink")) {
    const FieldReader gf(*g, "status.reply.openigtlink");
    r.openigtlink = OpenIgtlinkInfo{gf.uint("port"), gf.uint("clients"), gf.uint("messages_sent"),
                                    gf.uint("messages_dropped")};
  }
  return r;
}

// ---- preop.load ------------------------------------------------------------

Message make_preop_load_request(const std::string& request_id, const PreopLoadRequest& r) {
  Message m = make_message(MessageType::kPreopLoad, request_id);
  m.header["use_default_atlas"] = r.use_default_atlas;
  if (r.patient_id) m.header["patient_id"] = *r.patient_id;
  for (const auto* f : {&r.t1, &r.labels, &r.label_table})
    if (*f) m.frames.push_back(**f);
  return m;
}

PreopLoadRequest parse_preop_load_request(const Message& m) {
  expect_type(m, MessageType::kPreopLoad);
  return with_request_id(m, [&] {
    const FieldReader f(m.header, "preop.load");
    PreopLoadRequest r;
    r.use_default_atlas = f.boolean("use_default_atlas", false);
    r.patient_id = patient_id_field(f);
    if (r.use_default_atlas && r.patient_id)
      f.fail("patient_id", "names the patient of uploaded preop images; the default atlas is no patient's");
    if (r.use_default_atlas) {
      expect_frames(m, {});
      return r;
    }
    expect_frames(m, {"t1", "labels", "label_table"});
    r.t1 = get_frame(m, "t1", nifti_media);
    r.labels = get_frame(m, "labels", nifti_media);
    // Bounded before its JSON is even checked.
    if (const Frame* t = m.find_frame("label_table"); t && t->bytes.size() > kMaxLabelTableBytes)
      throw ProtocolError(ErrorCode::kInvalidRequest,
                          "preop.load: frame \"label_table\" is " + std::to_string(t->bytes.size()) +
                              " bytes; a label table is at most " + std::to_string(kMaxLabelTableBytes));
    r.label_table = get_frame(m, "label_table", json_media);
    if (!r.t1 || !r.labels)
      throw ProtocolError(ErrorCode::kInvalidRequest,
                          "preop.load: frames \"t1\" and \"labels\" are required unless "
                          "use_default_atlas is true");
    if (r.label_table) r.label_map = parse_label_map_json(r.label_table->bytes);
    return r;
  });
}

Message make_preop_load_reply(const std::string& request_id, const PreopLoadReply& r) {
  Message m = make_message(MessageType::kPreopLoadReply, request_id);
  m.header["preop_id"] = r.preop_id;
  return m;
}

PreopLoadReply parse_preop_load_reply(const Message& m) {
  expect_type(m, MessageType::kPreopLoadReply);
  expect_frames(m, {});
  return {FieldReader(m.header, "preop.load.reply").string("preop_id")};
}

// ---- scan.push -------------------------------------------------------------

Message make_scan_push_request(const std::string& request_id, const ScanPushRequest& r) {
  Message m = make_message(MessageType::kScanPush, request_id);
  if (r.client_scan_id) m.header["client_scan_id"] = *r.client_scan_id;
  if (r.labels_use) m.header["labels_use"] = *r.labels_use;
  if (r.patient_id) m.header["patient_id"] = *r.patient_id;
  if (r.labels) m.frames.push_back(*r.labels);
  if (r.image) m.frames.push_back(*r.image);
  return m;
}

ScanPushRequest parse_scan_push_request(const Message& m) {
  expect_type(m, MessageType::kScanPush);
  return with_request_id(m, [&] {
    const FieldReader f(m.header, "scan.push");
    expect_frames(m, {"labels", "image"});
    ScanPushRequest r{get_frame(m, "labels", nifti_media), get_frame(m, "image", nifti_media),
                      f.opt_string("client_scan_id"), f.opt_string("labels_use"), patient_id_field(f)};
    if (!r.labels && !r.image)
      throw ProtocolError(ErrorCode::kInvalidRequest,
                          "scan.push: needs a frame \"labels\", \"image\" or both (an image alone is segmented)");
    if (r.labels_use && *r.labels_use != "refine" && *r.labels_use != "exact")
      f.fail("labels_use", "must be \"refine\" or \"exact\"");
    if (r.labels_use && !(r.labels && r.image))
      f.fail("labels_use", "says how labels are used with their image: it needs both frames");
    if (r.client_scan_id && !detail::is_valid_id(*r.client_scan_id))
      f.fail("client_scan_id", "must be 1..128 printable ASCII characters without spaces");
    return r;
  });
}

Message make_scan_push_reply(const std::string& request_id, const ScanPushReply& r) {
  Message m = make_message(MessageType::kScanPushReply, request_id);
  m.header["scan_id"] = r.scan_id;
  m.header["duplicate"] = r.duplicate;
  return m;
}

ScanPushReply parse_scan_push_reply(const Message& m) {
  expect_type(m, MessageType::kScanPushReply);
  expect_frames(m, {});
  const FieldReader f(m.header, "scan.push.reply");
  return {f.string("scan_id"), f.boolean("duplicate", false)};
}

// ---- scan.result -----------------------------------------------------------

Message make_scan_result_request(const std::string& request_id, const ScanResultRequest& r) {
  Message m = make_message(MessageType::kScanResult, request_id);
  m.header["scan_id"] = r.scan_id;
  std::vector<std::string> parts, structures;
  for (auto p : r.parts) parts.emplace_back(to_string(p));
  structures = r.structures;
  m.header["parts"] = string_array(parts);
  if (!structures.empty()) m.header["structures"] = string_array(structures);
  return m;
}

namespace {
template <class E, class FromString>
std::vector<E> parse_name_list(const FieldReader& f, const char* key, const json& list,
                               FromString from_string) {
  std::vector<E> out;
  for (const auto& item : list) {
    const auto v = item.is_string() ? from_string(item.get<std::string>()) : std::nullopt;
    if (!v) f.fail(key, "contains an unknown name " + item.dump());
    if (std::find(out.begin(), out.end(), *v) != out.end()) f.fail(key, "repeats " + item.dump());
    out.push_back(*v);
  }
  return out;
}
}  // namespace

ScanResultRequest parse_scan_result_request(const Message& m) {
  expect_type(m, MessageType::kScanResult);
  return with_request_id(m, [&] {
    expect_frames(m, {});
    const FieldReader f(m.header, "scan.result");
    ScanResultRequest r;
    r.scan_id = f.string("scan_id");
    if (!detail::is_valid_id(r.scan_id))
      f.fail("scan_id", "must be 1..128 printable ASCII characters without spaces");
    r.parts = parse_name_list<ResultPart>(f, "parts", f.array("parts"), result_part_from_string);
    if (r.parts.empty()) f.fail("parts", "must name at least one part");
    if (const json* s = f.opt_array("structures")) {
      if (s->size() > kMaxStructures)
        f.fail("structures", "names more than " + std::to_string(kMaxStructures) + " structures");
      r.structures = parse_name_list<std::string>(f, "structures", *s, [](const std::string& name) {
        return is_valid_structure_name(name) ? std::optional<std::string>(name) : std::nullopt;
      });
    }
    return r;
  });
}

const Frame* ScanResultReply::find(std::string_view name) const {
  for (const auto& f : frames)
    if (f.name == name) return &f;
  return nullptr;
}

Message make_scan_result_reply(const std::string& request_id, const ScanResultReply& r) {
  Message m = with_frames(make_message(MessageType::kScanResultReply, request_id), r.frames);
  m.header["scan_id"] = r.scan_id;
  if (r.result) add_result_kind(m.header, *r.result);
  json unavailable = json::array();
  for (const auto& u : r.unavailable) {
    json entry{{"part", u.part}, {"reason", u.reason}};
    if (u.pending) entry["pending"] = true;  // optional field: absent means false
    unavailable.push_back(std::move(entry));
  }
  m.header["unavailable"] = unavailable;
  return m;
}

namespace {
// The media type each result frame must have (PROTOCOL.md, scan.result).
bool result_media_ok(const std::string& name, std::string_view type) {
  if (structure_of_model_frame(name)) return media_type_fits(ResultPart::kModels, type);
  const auto part = result_part_from_string(name);
  return part && *part != ResultPart::kModels && media_type_fits(*part, type);
}
}  // namespace

ScanResultReply parse_scan_result_reply(const Message& m) {
  expect_type(m, MessageType::kScanResultReply);
  const FieldReader f(m.header, "scan.result.reply");
  ScanResultReply r;
  r.scan_id = f.string("scan_id");
  r.result = result_kind_from_json(m.header, "scan.result.reply");
  for (const auto& frame : m.frames) {
    if (!result_media_ok(frame.name, frame.media_type))
      throw ProtocolError(ErrorCode::kInvalidRequest,
                          "scan.result.reply: unexpected frame \"" + frame.name + "\" (" +
                              frame.media_type + ")");
    media::check_content(frame);  // catches a server writing the wrong file
    r.frames.push_back(frame);
  }
  if (const json* list = f.opt_array("unavailable"))
    for (const auto& u : *list) {
      const FieldReader uf(u, "scan.result.reply.unavailable");
      r.unavailable.push_back({uf.string("part"), uf.text("reason"), uf.boolean("pending", false)});
    }
  return r;
}

// ---- scan.list -------------------------------------------------------------

Message make_scan_list_request(const std::string& request_id, const ScanListRequest& r) {
  Message m = make_message(MessageType::kScanList, request_id);
  m.header["limit"] = r.limit;
  return m;
}

ScanListRequest parse_scan_list_request(const Message& m) {
  expect_type(m, MessageType::kScanList);
  return with_request_id(m, [&] {
    expect_frames(m, {});
    const FieldReader f(m.header, "scan.list");
    ScanListRequest r;
    r.limit = f.opt_uint("limit").value_or(r.limit);
    if (r.limit < 1 || r.limit > kMaxScanListLimit)
      f.fail("limit", "must lie in 1.." + std::to_string(kMaxScanListLimit));
    return r;
  });
}

Message make_scan_list_reply(const std::string& request_id, const ScanListReply& r) {
  Message m = make_message(MessageType::kScanListReply, request_id);
  json scans = json::array();
  for (const auto& s : r.scans) {
    json j{{"scan_id", s.scan_id}, {"state", std::string(to_string(s.state))},
           {"received_at", s.received_at}};
    if (s.client_scan_id) j["client_scan_id"] = *s.client_scan_id;
    if (s.finished_at) j["finished_at"] = *s.finished_at;
    if (s.stage) j["stage"] = *s.stage;
    if (s.error) j["error"] = to_json_value(*s.error);
    if (s.result) add_result_kind(j, *s.result);
    scans.push_back(std::move(j));
  }
  m.header["scans"] = std::move(scans);
  return m;
}

ScanListReply parse_scan_list_reply(const Message& m) {
  expect_type(m, MessageType::kScanListReply);
  expect_frames(m, {});
  const FieldReader f(m.header, "scan.list.reply");
  ScanListReply r;
  for (const auto& item : f.array("scans")) {
    const FieldReader s(item, "scan.list.reply.scans[]");
    ScanSummary sum;
    sum.scan_id = s.string("scan_id");
    sum.client_scan_id = s.opt_string("client_scan_id");
    const auto state = scan_state_from_string(s.string("state"));
    if (!state) s.fail("state", "is not a known scan state");
    sum.state = *state;
    sum.received_at = s.string("received_at");
    sum.finished_at = s.opt_string("finished_at");
    sum.stage = s.opt_string("stage");
    if (const json* e = s.opt_object("error")) sum.error = error_info_from_json(*e, "scan.list.reply.scans[].error");
    sum.result = result_kind_from_json(item, "scan.list.reply.scans[]");
    r.scans.push_back(std::move(sum));
  }
  return r;
}

// ---- shutdown --------------------------------------------------------------

Message make_shutdown_request(const std::string& request_id, const ShutdownRequest& r) {
  Message m = make_message(MessageType::kShutdown, request_id);
  if (!r.reason.empty()) m.header["reason"] = r.reason;
  return m;
}

ShutdownRequest parse_shutdown_request(const Message& m) {
  expect_type(m, MessageType::kShutdown);
  return with_request_id(m, [&] {
    expect_frames(m, {});
    const FieldReader f(m.header, "shutdown");
    ShutdownRequest r{f.text("reason")};
    if (r.reason.size() > kMaxShutdownReasonLength)
      f.fail("reason", "at most " + std::to_string(kMaxShutdownReasonLength) + " characters");
    return r;
  });
}

Message make_shutdown_reply(const std::string& request_id) {
  return make_message(MessageType::kShutdownReply, request_id);
}

void parse_shutdown_reply(const Message& m) {
  expect_type(m, MessageType::kShutdownReply);
  expect_frames(m, {});
}

// ---- error -----------------------------------------------------------------

Message make_error_reply(const std::string& request_id, ErrorCode code, const std::string& message) {
  Message m = make_message(MessageType::kError, request_id);
  m.header["error"] = to_json_value(ErrorInfo{code, message});
  return m;
}

Message make_error_reply(const ProtocolError& error, const std::string& fallback_request_id) {
  // An unreadable id (too long, not ASCII) must not make the error reply itself invalid.
  std::string id = error.request_id().value_or(fallback_request_id);
  if (id.size() > Limits{}.max_request_id_length || !detail::is_valid_id(id)) id.clear();
  return make_error_reply(id, error.code(), error.what());
}

ErrorInfo parse_error_reply(const Message& m) {
  if (m.type() != MessageType::kError)
    throw ProtocolError(ErrorCode::kInvalidRequest,
                        "expected an error message, got " + std::string(to_string(m.type())));
  return error_info_from_json(FieldReader(m.header, "error").object("error"), "error.error");
}

void throw_if_error(const Message& m) {
  if (m.type() != MessageType::kError) return;
  const ErrorInfo e = parse_error_reply(m);
  throw ProtocolError(e.code, e.message, m.request_id());
}

}  // namespace brainshift::protocol
