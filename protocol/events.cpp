#include "protocol/events.h"

#include "protocol/fields.h"

namespace brainshift::protocol {
namespace {

using nlohmann::json;
using detail::FieldReader;

Message event(MessageType type) {
  Message m = make_message(type, "");
  m.header["t"] = utc_now();
  return m;
}

// Checks type, absence of frames and the publication time; returns a reader.
FieldReader open_event(const Message& m, MessageType expected) {
  const auto name = std::string(to_string(expected));
  if (m.type() != expected)
    throw ProtocolError(ErrorCode::kInvalidRequest,
                        "expected " + name + ", got " + std::string(to_string(m.type())));
  if (!m.frames.empty())
    throw ProtocolError(ErrorCode::kInvalidRequest, name + ": events carry no binary frames");
  FieldReader f(m.header, name);
  if (!is_iso8601_utc(f.string("t"))) f.fail("t", "must be ISO-8601 UTC");
  return f;
}

}  // namespace

Message make_event(const PreopProgressEvent& e) {
  Message m = event(MessageType::kEventPreopProgress);
  m.header.update({{"preop_id", e.preop_id}, {"stage", e.stage}, {"fraction", e.fraction}});
  return m;
}

Message make_event(const PreopReadyEvent& e) {
  Message m = event(MessageType::kEventPreopReady);
  m.header.update({{"preop_id", e.preop_id}, {"mesh", to_json_value(e.mesh)}, {"seconds", e.seconds}});
  return m;
}

Message make_event(const PreopFailedEvent& e) {
  Message m = event(MessageType::kEventPreopFailed);
  m.header.update({{"preop_id", e.preop_id}, {"error", to_json_value(e.error)}});
  return m;
}

Message make_event(const StageEvent& e) {
  Message m = event(MessageType::kEventStage);
  m.header["timing"] = to_json_value(e.timing);
  return m;
}

Message make_event(const ScanProgressEvent& e) {
  Message m = event(MessageType::kEventScanProgress);
  m.header.update({{"scan_id", e.scan_id}, {"stage", e.stage}, {"fraction", e.fraction}});
  return m;
}

Message make_event(const ScanDoneEvent& e) {
  Message m = event(MessageType::kEventScanDone);
  m.header.update({{"scan_id", e.scan_id}, {"seconds", e.seconds}});
  if (e.client_scan_id) m.header["client_scan_id"] = *e.client_scan_id;
  if (e.result) add_result_kind(m.header, *e.result);
  return m;
}

Message make_event(const ScanFailedEvent& e) {
  Message m = event(MessageType::kEventScanFailed);
  m.header.update({{"scan_id", e.scan_id}, {"stage", e.stage}, {"error", to_json_value(e.error)}});
  if (e.client_scan_id) m.header["client_scan_id"] = *e.client_scan_id;
  return m;
}

Message make_event(const ServerShutdownEvent& e) {
  Message m = event(MessageType::kEventServerShutdown);
  m.header["reason"] = e.reason;
  return m;
}

PreopProgressEvent parse_preop_progress_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventPreopProgress);
  return {f.string("preop_id"), f.string("stage"), f.fraction("fraction")};
}

PreopReadyEvent parse_preop_ready_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventPreopReady);
  return {f.string("preop_id"), mesh_size_from_json(f.object("mesh"), "event.preop.ready.mesh"),
          f.number("seconds")};
}

PreopFailedEvent parse_preop_failed_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventPreopFailed);
  return {f.string("preop_id"), error_info_from_json(f.object("error"), "event.preop.failed.error")};
}

StageEvent parse_stage_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventStage);
  return {stage_timing_from_json(f.object("timing"))};
}

ScanProgressEvent parse_scan_progress_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventScanProgress);
  return {f.string("scan_id"), f.string("stage"), f.fraction("fraction")};
}

ScanDoneEvent parse_scan_done_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventScanDone);
  return {f.string("scan_id"), f.opt_string("client_scan_id"), f.number("seconds"),
          result_kind_from_json(m.header, "event.scan.done")};
}

ScanFailedEvent parse_scan_failed_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventScanFailed);
  return {f.string("scan_id"), f.opt_string("client_scan_id"), f.string("stage"),
          error_info_from_json(f.object("error"), "event.scan.failed.error")};
}

ServerShutdownEvent parse_server_shutdown_event(const Message& m) {
  const auto f = open_event(m, MessageType::kEventServerShutdown);
  return {f.text("reason")};
}

}  // namespace brainshift::protocol
