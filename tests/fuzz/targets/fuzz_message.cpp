// libFuzzer target: the protocol decoder and the typed parsers, driven the way
// brainshiftd drives them (ServerCore::handle_wire) plus the client side
// (replies, events). The input is split into frames (wire_split.h).
//
// Oracles, besides ASan/UBSan:
// - the only exception that may leave the codec is ProtocolError (anything
//   else would reach the client as "internal" instead of a typed error);
// - every refusal yields an error reply that encodes, decodes and carries the
//   same code (the server must always be able to answer);
// - whatever parses survives a round trip through its builder unchanged.
#include <cstdio>
#include <cstdlib>

#include "protocol/events.h"
#include "protocol/fields.h"
#include "protocol/requests.h"
#include "wire_split.h"

namespace {

using namespace brainshift::protocol;

[[noreturn]] void violated(const char* what) {
  std::fprintf(stderr, "fuzz_message: property violated: %s\n", what);
  std::abort();
}

void require(bool ok, const char* what) {
  if (!ok) violated(what);
}

Message reencode(const Message& m) {
  return decode(encode(m), Limits::client_inbound());
}

bool same_frame(const std::optional<Frame>& a, const std::optional<Frame>& b) {
  if (a.has_value() != b.has_value()) return false;
  return !a || (a->name == b->name && a->media_type == b->media_type && a->bytes == b->bytes);
}

void round_trip_request(const Message& m) {
  const std::string id = m.request_id();
  switch (m.type()) {
    case MessageType::kStatus:
      parse_status_request(m);
      parse_status_request(reencode(make_status_request(id)));
      break;
    case MessageType::kPreopLoad: {
      const PreopLoadRequest r = parse_preop_load_request(m);
      const PreopLoadRequest back = parse_preop_load_request(reencode(make_preop_load_request(id, r)));
      require(back.use_default_atlas == r.use_default_atlas && same_frame(back.t1, r.t1) &&
                  same_frame(back.labels, r.labels) && same_frame(back.label_table, r.label_table),
              "preop.load round trip");
      break;
    }
    case MessageType::kScanPush: {
      const ScanPushRequest r = parse_scan_push_request(m);
      const ScanPushRequest back = parse_scan_push_request(reencode(make_scan_push_request(id, r)));
      require(same_frame(back.labels, r.labels) && same_frame(back.image, r.image) &&
                  back.client_scan_id == r.client_scan_id,
              "scan.push round trip");
      break;
    }
    case MessageType::kScanResult: {
      const ScanResultRequest r = parse_scan_result_request(m);
      require(parse_scan_result_request(reencode(make_scan_result_request(id, r))) == r, "scan.result round trip");
      break;
    }
    case MessageType::kScanList: {
      const ScanListRequest r = parse_scan_list_request(m);
      require(parse_scan_list_request(reencode(make_scan_list_request(id, r))) == r, "scan.list round trip");
      break;
    }
    case MessageType::kLabelsGet:
      parse_labels_request(m);
      parse_labels_request(reencode(make_labels_request(id)));
      break;
    case MessageType::kShutdown: {
      const ShutdownRequest r = parse_shutdown_request(m);
      require(parse_shutdown_request(reencode(make_shutdown_request(id, r))) == r, "shutdown round trip");
      break;
    }
    default:
      violated("round_trip_request called for a non-request");
  }
}

void round_trip_reply(const Message& m) {
  const std::string id = m.request_id();
  switch (m.type()) {
    case MessageType::kStatusReply: {
      StatusReply r = parse_status_reply(m);
      r.versions["protocol"] = std::to_string(1);  // the builder always states its own version
      require(parse_status_reply(reencode(make_status_reply(id, r))) == r, "status.reply round trip");
      break;
    }
    case MessageType::kPreopLoadReply: {
      const PreopLoadReply r = parse_preop_load_reply(m);
      require(parse_preop_load_reply(reencode(make_preop_load_reply(id, r))) == r, "preop.load.reply round trip");
      break;
    }
    case MessageType::kScanPushReply: {
      const ScanPushReply r = parse_scan_push_reply(m);
      require(parse_scan_push_reply(reencode(make_scan_push_reply(id, r))) == r, "scan.push.reply round trip");
      break;
    }
    case MessageType::kScanResultReply: {
      const ScanResultReply r = parse_scan_result_reply(m);
      const ScanResultReply back = parse_scan_result_reply(reencode(make_scan_result_reply(id, r)));
      require(back.scan_id == r.scan_id && back.unavailable == r.unavailable && back.frames.size() == r.frames.size(),
              "scan.result.reply round trip");
      if (const Frame* t = r.find("timings")) parse_timings_json(t->bytes);
      break;
    }
    case MessageType::kScanListReply: {
      const ScanListReply r = parse_scan_list_reply(m);
      require(parse_scan_list_reply(reencode(make_scan_list_reply(id, r))) == r, "scan.list.reply round trip");
      break;
    }
    case MessageType::kLabelsGetReply: {
      const LabelsReply r = parse_labels_reply(m);
      require(parse_labels_reply(reencode(make_labels_reply(id, r))) == r, "labels.get.reply round trip");
      break;
    }
    case MessageType::kShutdownReply:
      parse_shutdown_reply(m);
      break;
    case MessageType::kError: {
      const ErrorInfo e = parse_error_reply(m);
      require(parse_error_reply(reencode(make_error_reply(id, e.code, e.message))) == e, "error round trip");
      break;
    }
    default:
      violated("round_trip_reply called for a non-reply");
  }
}

template <class Event, class Parse>
void round_trip_event(const Message& m, Parse parse) {
  const Event e = parse(m);
  require(parse(reencode(make_event(e))) == e, "event round trip");
}

void round_trip_event_any(const Message& m) {
  switch (m.type()) {
    case MessageType::kEventPreopProgress: return round_trip_event<PreopProgressEvent>(m, parse_preop_progress_event);
    case MessageType::kEventPreopReady: return round_trip_event<PreopReadyEvent>(m, parse_preop_ready_event);
    case MessageType::kEventPreopFailed: return round_trip_event<PreopFailedEvent>(m, parse_preop_failed_event);
    case MessageType::kEventStage: return round_trip_event<StageEvent>(m, parse_stage_event);
    case MessageType::kEventScanProgress: return round_trip_event<ScanProgressEvent>(m, parse_scan_progress_event);
    case MessageType::kEventScanDone: return round_trip_event<ScanDoneEvent>(m, parse_scan_done_event);
    case MessageType::kEventScanFailed: return round_trip_event<ScanFailedEvent>(m, parse_scan_failed_event);
    case MessageType::kEventServerShutdown:
      return round_trip_event<ServerShutdownEvent>(m, parse_server_shutdown_event);
    default: violated("round_trip_event_any called for a non-event");
  }
}

// The server's answer to a refused request must itself be a valid message.
void check_error_reply(const ProtocolError& e) {
  const Message reply = make_error_reply(e);
  const Message back = decode(encode(reply), Limits::client_inbound());
  require(parse_error_reply(back).code == e.code(), "error reply keeps the code");
  if (e.request_id() && detail::is_valid_id(*e.request_id()))
    require(back.request_id() == *e.request_id(), "error reply echoes a readable request id");
}

void exercise(std::vector<std::string> wire, const Limits& limits) {
  try {
    const Message m = decode(std::move(wire), limits);
    switch (kind_of(m.type())) {
      case MessageKind::kRequest: round_trip_request(m); break;
      case MessageKind::kReply: round_trip_reply(m); break;
      case MessageKind::kEvent: round_trip_event_any(m); break;
    }
  } catch (const ProtocolError& e) {
    check_error_reply(e);
  }
}

// Small limits make the too_large paths reachable with small inputs.
Limits small_limits() {
  Limits l;
  l.max_header_bytes = 2048;
  l.max_frame_bytes = 1024;
  l.max_total_bytes = 1536;
  l.max_frames = 3;
  l.max_request_id_length = 32;
  return l;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const auto wire = brainshift::fuzz::split_frames(input);
  exercise(wire, Limits::server_inbound());
  exercise(wire, small_limits());
  try {
    decode_request(wire, Limits::server_inbound());
  } catch (const ProtocolError& e) {
    check_error_reply(e);
  }
  return 0;
}
