#pragma once
// Typed builders and parsers for every request and reply (PROTOCOL.md,
// "Requests"). make_* returns a Message ready for encode(); parse_* takes a
// decoded Message, checks its type, fields and frames, and throws
// ProtocolError(kInvalidRequest) naming what is wrong. The server parses
// requests and builds replies; the client does the opposite.
#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "protocol/common.h"
#include "protocol/label_tables.h"
#include "protocol/message.h"
#include "protocol/result_outputs.h"

namespace brainshift::protocol {

// ---- Enumerations with wire names -----------------------------------------

enum class ServerState { kIdle, kLoadingPreop, kReady, kProcessing };
enum class ScanState { kQueued, kProcessing, kDone, kFailed };
std::string_view to_string(ServerState s);
std::string_view to_string(ScanState s);
std::optional<ServerState> server_state_from_string(std::string_view s);
std::optional<ScanState> scan_state_from_string(std::string_view s);

// Bounds on what a client sends (PROTOCOL.md section 13.5); the label
// table's are in protocol/label_tables.h.
inline constexpr std::size_t kMaxShutdownReasonLength = 256;

// ---- status ----------------------------------------------------------------

struct StatusRequest {};
Message make_status_request(const std::string& request_id);
StatusRequest parse_status_request(const Message& m);

struct Progress {
  std::string stage{};      // current warm-up stage, e.g. "mesh"
  double fraction = 0.0;  // of the whole warm-up, in [0, 1]
  bool operator==(const Progress&) const = default;
};
struct QueueInfo {
  std::uint64_t depth = 0;     // scans waiting, not counting the one running
  std::uint64_t capacity = 0;  // scan.push beyond this gets "busy"
  bool operator==(const QueueInfo&) const = default;
};
// The OpenIGTLink gateway's counters (PROTOCOL.md section 16), when it runs.
struct OpenIgtlinkInfo {
  std::uint64_t port = 0;              // TCP port it listens on
  std::uint64_t clients = 0;           // connected now
  std::uint64_t messages_sent = 0;     // whole messages written, all clients, since start
  std::uint64_t messages_dropped = 0;  // oldest unsent messages dropped from full client queues
  bool operator==(const OpenIgtlinkInfo&) const = default;
};

struct StatusReply {
  ServerState state = ServerState::kIdle;
  std::optional<Progress> progress{};             // present while kLoadingPreop
  std::map<std::string, std::string> versions{};  // "protocol" is always added
  std::optional<std::string> preop_id{};          // loaded or loading preop
  std::optional<std::string> preop_patient_id{};  // that preop's patient, when preop.load named one
  std::optional<MeshSize> mesh{};                 // once the preop is ready
  std::uint64_t mpi_ranks = 1;
  QueueInfo queue{};
  std::optional<std::string> current_scan_id{};  // present while kProcessing
  std::optional<ErrorInfo> last_error{};         // last failed preop.load, if any
  std::optional<OpenIgtlinkInfo> openigtlink{};  // when the OpenIGTLink gateway is on
  bool operator==(const StatusReply&) const = default;
};
Message make_status_reply(const std::string& request_id, const StatusReply& r);
StatusReply parse_status_reply(const Message& m);

// ---- preop.load ------------------------------------------------------------

struct PreopLoadRequest {
  bool use_default_atlas = false;
  std::optional<Frame> t1{};           // "t1", NIfTI, required unless default atlas
  std::optional<Frame> labels{};       // "labels", NIfTI, same grid as t1
  std::optional<Frame> label_table{};  // "label_table", JSON, optional
  std::optional<LabelMap> label_map{};  // label_table parsed by parse_preop_load_request
  // The patient the preop images are of (DICOM PatientID); scans pushed with
  // another patient's id are refused (PROTOCOL.md, "Patient identity").
  std::optional<std::string> patient_id{};
};
Message make_preop_load_request(const std::string& request_id, const PreopLoadRequest& r);
PreopLoadRequest parse_preop_load_request(const Message& m);  // moves nothing; copies frames

struct PreopLoadReply {
  std::string preop_id{};  // names the warm-up in events and status
  bool operator==(const PreopLoadReply&) const = default;
};
Message make_preop_load_reply(const std::string& request_id, const PreopLoadReply& r);
PreopLoadReply parse_preop_load_reply(const Message& m);

// ---- scan.push -------------------------------------------------------------

// At least one of labels and image (revision 4): an image alone is segmented
// by the engine, and the result then has intraop_labels and
// segmentation_confidence (result_outputs.h).
struct ScanPushRequest {
  std::optional<Frame> labels{};                // "labels", NIfTI, intraop segmentation
  std::optional<Frame> image{};                 // "image", NIfTI, intraop image
  std::optional<std::string> client_scan_id{};  // idempotence key, see PROTOCOL.md
  // With both frames: "refine" (the image is classified under the labels)
  // or "exact" (the labels as given); absent: the server's configuration.
  std::optional<std::string> labels_use{};
  std::optional<std::string> patient_id{};  // the scan's patient (DICOM PatientID), checked against the preop's
};
Message make_scan_push_request(const std::string& request_id, const ScanPushRequest& r);
ScanPushRequest parse_scan_push_request(const Message& m);

struct ScanPushReply {
  std::string scan_id{};
  bool duplicate = false;  // true: client_scan_id was seen before, nothing new stored
  bool operator==(const ScanPushReply&) const = default;
};
Message make_scan_push_reply(const std::string& request_id, const ScanPushReply& r);
ScanPushReply parse_scan_push_reply(const Message& m);

// ---- scan.result -----------------------------------------------------------

struct ScanResultRequest {
  std::string scan_id{};
  std::vector<ResultPart> parts{};      // non-empty, no repeats
  std::vector<std::string> structures{};  // for kModels; empty = all the result has
  bool operator==(const ScanResultRequest&) const = default;
};
Message make_scan_result_request(const std::string& request_id, const ScanResultRequest& r);
ScanResultRequest parse_scan_result_request(const Message& m);

struct UnavailablePart {
  std::string part{};    // a frame name, e.g. "warped_image" or "model.tumor"
  std::string reason{};  // e.g. "no intraop image was pushed"
  // True when the part is still being produced (report.png is rendered after
  // event.scan.done): ask again shortly. False: it will never exist.
  bool pending = false;
  bool operator==(const UnavailablePart&) const = default;
};
struct ScanResultReply {
  std::string scan_id{};
  std::optional<ResultKindInfo> result{};  // always sent; absent from older servers
  std::vector<Frame> frames{};  // named by frame_name / model_frame_name
  std::vector<UnavailablePart> unavailable{};
  const Frame* find(std::string_view name) const;
};
Message make_scan_result_reply(const std::string& request_id, const ScanResultReply& r);
ScanResultReply parse_scan_result_reply(const Message& m);

// ---- scan.list -------------------------------------------------------------

inline constexpr std::uint64_t kMaxScanListLimit = 1000;
struct ScanListRequest {
  std::uint64_t limit = 100;  // newest first, 1..kMaxScanListLimit
  bool operator==(const ScanListRequest&) const = default;
};
Message make_scan_list_request(const std::string& request_id, const ScanListRequest& r = {});
ScanListRequest parse_scan_list_request(const Message& m);

struct ScanSummary {
  std::string scan_id{};
  std::optional<std::string> client_scan_id{};
  ScanState state = ScanState::kQueued;
  std::string received_at{};                 // ISO-8601 UTC
  std::optional<std::string> finished_at{};  // done or failed
  std::optional<std::string> stage{};        // running stage while kProcessing
  std::optional<ErrorInfo> error{};          // when kFailed
  std::optional<ResultKindInfo> result{};    // when kDone (absent from older servers)
  bool operator==(const ScanSummary&) const = default;
};
struct ScanListReply {
  std::vector<ScanSummary> scans{};
  bool operator==(const ScanListReply&) const = default;
};
Message make_scan_list_reply(const std::string& request_id, const ScanListReply& r);
ScanListReply parse_scan_list_reply(const Message& m);

// ---- shutdown --------------------------------------------------------------

struct ShutdownRequest {
  std::string reason{};  // optional, logged and echoed in event.server.shutdown
  bool operator==(const ShutdownRequest&) const = default;
};
Message make_shutdown_request(const std::string& request_id, const ShutdownRequest& r = {});
ShutdownRequest parse_shutdown_request(const Message& m);
Message make_shutdown_reply(const std::string& request_id);
void parse_shutdown_reply(const Message& m);

// ---- error -----------------------------------------------------------------

// request_id may be "" when the request's id could not be read.
Message make_error_reply(const std::string& request_id, ErrorCode code, const std::string& message);
// Uses the error's request_id when it has one, else fallback_request_id.
Message make_error_reply(const ProtocolError& error, const std::string& fallback_request_id = "");
ErrorInfo parse_error_reply(const Message& m);
// For clients: throws ProtocolError (with the reply's code and request_id) if
// m is an error reply; does nothing otherwise.
void throw_if_error(const Message& m);

}  // namespace brainshift::protocol
