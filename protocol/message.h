#pragma once
// The transport-free codec: a Message is a JSON header plus named binary
// frames; on the wire it is [header JSON][frame 1 bytes]...[frame n bytes], and
// the header's "frames" manifest lists each frame's name, media type and size
// so that the receiver can check what arrived before it touches the bytes.
#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "protocol/error_codes.h"
#include "protocol/message_types.h"

namespace brainshift::protocol {

// Receiver-side limits (PROTOCOL.md, "Size limits"). The server keeps the
// defaults small enough for scans; a client pulling results needs larger ones,
// because a 0.5 mm displacement field alone is several hundred MB unzipped.
struct Limits {
  std::size_t max_header_bytes = 64 * 1024;
  std::size_t max_frame_bytes = std::size_t{256} << 20;
  std::size_t max_total_bytes = std::size_t{512} << 20;
  std::size_t max_frames = 32;
  std::size_t max_request_id_length = 128;
  // Arrays/objects nested deeper than this are refused before parsing: the
  // JSON library copies and prints values recursively, so a 64 KiB header of
  // brackets would otherwise overflow the stack (found by tests/fuzz).
  std::size_t max_header_depth = 32;

  static Limits server_inbound() { return Limits{}; }
  static Limits client_inbound() {
    Limits l;
    // A scan.list reply of kMaxScanListLimit scans is ~110 KiB of header
    // (measured: 600 scans did not fit in 64 KiB).
    l.max_header_bytes = std::size_t{1} << 20;
    l.max_frame_bytes = std::size_t{2} << 30;
    l.max_total_bytes = std::size_t{4} << 30;
    return l;
  }
};

// A binary frame. bytes is raw data (may contain NUL), never text-decoded.
struct Frame {
  std::string name{};        // [a-z0-9_.-]{1,64}, unique within a message
  std::string media_type{};  // see media.h
  std::string bytes{};
};

struct Message {
  nlohmann::json header = nlohmann::json::object();
  std::vector<Frame> frames{};

  // Throws ProtocolError(kUnknownType) if "type" is missing or unknown.
  MessageType type() const;
  // "" when absent (events, or an error reply to an unreadable request).
  std::string request_id() const;
  // nullptr when there is no frame of that name.
  const Frame* find_frame(std::string_view name) const;
};

// A message with the common header fields "v", "type" and "request_id" set.
// request_id may be empty only for events and error replies.
Message make_message(MessageType type, const std::string& request_id);

// Serialises the header (with "v" and a "frames" manifest generated from
// frames, replacing any given) and appends the frame bytes. Throws
// ProtocolError(kBadHeader) for a message that decode() would refuse
// (missing type or request_id, bad or duplicate frame names).
std::vector<std::string> encode(const Message& message);

// Validates everything that is common to all messages, in this order: sizes
// against limits, JSON, version, type, request_id, frames manifest, frames
// received against the manifest. Throws ProtocolError with the matching code;
// its request_id() is set whenever the header had a readable one.
Message decode(std::vector<std::string> wire, const Limits& limits = {});

// decode() for the ROUTER side: additionally refuses replies and events with
// kUnknownType, since only request types are requests.
Message decode_request(std::vector<std::string> wire, const Limits& limits = {});

// Deepest nesting of arrays and objects in JSON text, counted without parsing
// (strings skipped); exact for valid JSON, so it bounds what a parse would build.
std::size_t json_nesting_depth(std::string_view text);

// Frame-name rule shared by encode, decode and the typed builders.
bool is_valid_frame_name(std::string_view name);

}  // namespace brainshift::protocol
