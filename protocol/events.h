#pragma once
// Typed builders and parsers for the events published on the PUB socket
// (PROTOCOL.md, "Events"). The PUB topic is the event type string, so a
// monitor can subscribe to "event.scan." or "event.stage" alone.
#include <optional>
#include <string>

#include "protocol/common.h"
#include "protocol/message.h"
#include "protocol/timing_log.h"

namespace brainshift::protocol {

struct PreopProgressEvent {
  std::string preop_id{};
  std::string stage{};      // stage now running: atlas, mesh, assemble, factorise
  double fraction = 0.0;  // of the whole warm-up, in [0, 1]
  bool operator==(const PreopProgressEvent&) const = default;
};
struct PreopReadyEvent {
  std::string preop_id{};
  MeshSize mesh{};
  double seconds = 0.0;  // whole warm-up
  bool operator==(const PreopReadyEvent&) const = default;
};
struct PreopFailedEvent {
  std::string preop_id{};
  ErrorInfo error{};
  bool operator==(const PreopFailedEvent&) const = default;
};
struct StageEvent {
  StageTiming timing{};  // exactly the timing-log line
  bool operator==(const StageEvent&) const = default;
};
struct ScanProgressEvent {
  std::string scan_id{};
  std::string stage{};  // stage now running
  double fraction = 0.0;
  bool operator==(const ScanProgressEvent&) const = default;
};
struct ScanDoneEvent {
  std::string scan_id{};
  std::optional<std::string> client_scan_id{};
  double seconds = 0.0;  // intraop total
  std::optional<ResultKindInfo> result{};  // always sent; absent from older servers
  bool operator==(const ScanDoneEvent&) const = default;
};
struct ScanFailedEvent {
  std::string scan_id{};
  std::optional<std::string> client_scan_id{};
  std::string stage{};  // stage that failed
  ErrorInfo error{};
  bool operator==(const ScanFailedEvent&) const = default;
};
struct ServerShutdownEvent {
  std::string reason{};
  bool operator==(const ServerShutdownEvent&) const = default;
};

// Every event carries "t" (ISO-8601 UTC, publication time); the parsers check
// it but do not return it, except StageEvent whose timing has its own "t".
Message make_event(const PreopProgressEvent& e);
Message make_event(const PreopReadyEvent& e);
Message make_event(const PreopFailedEvent& e);
Message make_event(const StageEvent& e);
Message make_event(const ScanProgressEvent& e);
Message make_event(const ScanDoneEvent& e);
Message make_event(const ScanFailedEvent& e);
Message make_event(const ServerShutdownEvent& e);

PreopProgressEvent parse_preop_progress_event(const Message& m);
PreopReadyEvent parse_preop_ready_event(const Message& m);
PreopFailedEvent parse_preop_failed_event(const Message& m);
StageEvent parse_stage_event(const Message& m);
ScanProgressEvent parse_scan_progress_event(const Message& m);
ScanDoneEvent parse_scan_done_event(const Message& m);
ScanFailedEvent parse_scan_failed_event(const Message& m);
ServerShutdownEvent parse_server_shutdown_event(const Message& m);

}  // namespace brainshift::protocol
