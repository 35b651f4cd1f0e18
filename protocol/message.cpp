#include "protocol/message.h"

#include <set>
#include <utility>

#include "protocol/version.h"

namespace brainshift::protocol {
namespace {

using nlohmann::json;

constexpr std::size_t kMaxMediaTypeLength = 127;

bool is_visible_ascii(std::string_view s) {
  for (char c : s)
    if (c < 0x21 || c > 0x7e) return false;  // no spaces: ids end up in log lines
  return true;
}

// Sizes before content: nothing is parsed before we know it fits.
void check_header_size(const std::vector<std::string>& wire, const Limits& limits) {
  if (wire.empty()) throw ProtocolError(ErrorCode::kBadHeader, "empty message: no header frame");
  if (wire[0].size() > limits.max_header_bytes)
    throw ProtocolError(ErrorCode::kTooLarge,
                        "header frame is " + std::to_string(wire[0].size()) + " bytes; limit is " +
                            std::to_string(limits.max_header_bytes));
}

void check_frame_sizes(const std::vector<std::string>& wire, const Limits& limits) {
  if (wire.size() - 1 > limits.max_frames)
    throw ProtocolError(ErrorCode::kTooLarge,
                        std::to_string(wire.size() - 1) + " binary frames; limit is " +
                            std::to_string(limits.max_frames));
  std::size_t total = 0;
  for (std::size_t i = 1; i < wire.size(); ++i) {
    if (wire[i].size() > limits.max_frame_bytes)
      throw ProtocolError(ErrorCode::kTooLarge,
                          "frame " + std::to_string(i) + " is " + std::to_string(wire[i].size()) +
                              " bytes; limit is " + std::to_string(limits.max_frame_bytes));
    total += wire[i].size();
  }
  if (total > limits.max_total_bytes)
    throw ProtocolError(ErrorCode::kTooLarge, "message carries " + std::to_string(total) +
                                                  " bytes of frames; limit is " +
                                                  std::to_string(limits.max_total_bytes));
}

json parse_header(const std::string& text) {
  json header = json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (header.is_discarded())
    throw ProtocolError(ErrorCode::kMalformedJson, "header frame is not valid JSON");
  if (!header.is_object())
    throw ProtocolError(ErrorCode::kMalformedJson, "header frame must be a JSON object");
  return header;
}

void check_version(const json& header) {
  const auto it = header.find("v");
  if (it == header.end())
    throw ProtocolError(ErrorCode::kVersionMismatch,
                        "header has no \"v\"; this peer speaks protocol version " +
                            std::to_string(kProtocolVersion));
  if (!it->is_number_integer() || it->get<long long>() != kProtocolVersion)
    throw ProtocolError(ErrorCode::kVersionMismatch,
                        "protocol version " + it->dump() + " is not supported; this peer speaks " +
                            std::to_string(kProtocolVersion));
}

MessageType check_type(const json& header) {
  const auto it = header.find("type");
  if (it == header.end() || !it->is_string())
    throw ProtocolError(ErrorCode::kBadHeader, "header needs \"type\" (string)");
  const auto type = message_type_from_string(it->get<std::string>());
  if (!type)
    throw ProtocolError(ErrorCode::kUnknownType,
                        "unknown message type \"" + it->get<std::string>() + "\"");
  return *type;
}

// Returns the id if the header has a readable one, whether or not it is valid,
// so that errors found later can still be answered to the right request.
std::optional<std::string> readable_request_id(const json& header) {
  const auto it = header.find("request_id");
  if (it == header.end() || !it->is_string()) return std::nullopt;
  return it->get<std::string>();
}

void check_request_id(const json& header, MessageType type, const Limits& limits) {
  const auto it = header.find("request_id");
  const auto kind = kind_of(type);
  // Events may omit it; an error reply to an unreadable request carries "".
  if (it == header.end() && kind == MessageKind::kEvent) return;
  if (it == header.end() || !it->is_string())
    throw ProtocolError(ErrorCode::kBadHeader, "header needs \"request_id\" (string)");
  const auto& id = it->get_ref<const std::string&>();
  const bool may_be_empty = kind == MessageKind::kEvent || type == MessageType::kError;
  if (id.empty() && !may_be_empty)
    throw ProtocolError(ErrorCode::kBadHeader, "\"request_id\" must not be empty");
  if (id.size() > limits.max_request_id_length || !is_visible_ascii(id))
    throw ProtocolError(ErrorCode::kBadHeader,
                        "\"request_id\" must be printable ASCII without spaces, at most " +
                            std::to_string(limits.max_request_id_length) + " characters");
}

struct Declared {
  std::string name, media_type;
  std::size_t size = 0;
};

Declared parse_manifest_entry(const json& entry, std::size_t index) {
  const std::string where = "frames[" + std::to_string(index) + "]";
  if (!entry.is_object()) throw ProtocolError(ErrorCode::kBadHeader, where + " must be an object");
  const auto name = entry.find("name");
  const auto media = entry.find("media_type");
  const auto size = entry.find("size");
  if (name == entry.end() || !name->is_string() || !is_valid_frame_name(name->get<std::string>()))
    throw ProtocolError(ErrorCode::kBadHeader, where + ".name must match [a-z0-9_.-]{1,64}");
  if (media == entry.end() || !media->is_string() || media->get<std::string>().empty() ||
      media->get<std::string>().size() > kMaxMediaTypeLength)
    throw ProtocolError(ErrorCode::kBadHeader, where + ".media_type must be a non-empty string");
  const bool non_negative_integer =
      size != entry.end() && size->is_number_integer() &&
      (size->is_number_unsigned() || size->get<std::int64_t>() >= 0);
  if (!non_negative_integer)
    throw ProtocolError(ErrorCode::kBadHeader, where + ".size must be a non-negative integer");
  return {name->get<std::string>(), media->get<std::string>(), size->get<std::size_t>()};
}

std::vector<Declared> parse_manifest(const json& header, const Limits& limits) {
  std::vector<Declared> declared;
  const auto it = header.find("frames");
  if (it == header.end()) return declared;  // no binary frames
  if (!it->is_array()) throw ProtocolError(ErrorCode::kBadHeader, "\"frames\" must be an array");
  // Counted before any entry is read (a 64 KiB header can list thousands).
  if (it->size() > limits.max_frames)
    throw ProtocolError(ErrorCode::kTooLarge, "\"frames\" lists " + std::to_string(it->size()) +
                                                  " frames; limit is " + std::to_string(limits.max_frames));
  std::set<std::string> names;
  for (std::size_t i = 0; i < it->size(); ++i) {
    declared.push_back(parse_manifest_entry((*it)[i], i));
    if (!names.insert(declared.back().name).second)
      throw ProtocolError(ErrorCode::kBadHeader,
                          "frame name \"" + declared.back().name + "\" appears twice");
  }
  return declared;
}

void match_frames(const std::vector<Declared>& declared, const std::vector<std::string>& wire) {
  if (declared.size() != wire.size() - 1)
    throw ProtocolError(ErrorCode::kFrameCountMismatch,
                        "header declares " + std::to_string(declared.size()) +
                            " binary frames but " + std::to_string(wire.size() - 1) +
                            " were received");
  for (std::size_t i = 0; i < declared.size(); ++i)
    if (declared[i].size != wire[i + 1].size())
      throw ProtocolError(ErrorCode::kFrameSizeMismatch,
                          "frame \"" + declared[i].name + "\" declared " +
                              std::to_string(declared[i].size) + " bytes but " +
                              std::to_string(wire[i + 1].size()) + " were received");
}

}  // namespace

bool is_valid_frame_name(std::string_view name) {
  if (name.empty() || name.size() > 64) return false;
  for (char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_' || c == '.' ||
                    c == '-';
    if (!ok) return false;
  }
  return true;
}

MessageType Message::type() const {
  const auto it = header.find("type");
  if (it == header.end() || !it->is_string())
    throw ProtocolError(ErrorCode::kUnknownType, "message has no \"type\"");
  const auto t = message_type_from_string(it->get<std::string>());
  if (!t)
    throw ProtocolError(ErrorCode::kUnknownType,
                        "unknown message type \"" + it->get<std::string>() + "\"");
  return *t;
}

std::string Message::request_id() const {
  return readable_request_id(header).value_or("");
}

const Frame* Message::find_frame(std::string_view name) const {
  for (const auto& f : frames)
    if (f.name == name) return &f;
  return nullptr;
}

Message make_message(MessageType type, const std::string& request_id) {
  Message m;
  m.header["v"] = kProtocolVersion;
  m.header["type"] = std::string(to_string(type));
  if (!request_id.empty() || kind_of(type) != MessageKind::kEvent)
    m.header["request_id"] = request_id;
  return m;
}

std::vector<std::string> encode(const Message& message) {
  json header = message.header;
  header["v"] = kProtocolVersion;
  json manifest = json::array();
  std::set<std::string> names;
  for (const auto& f : message.frames) {
    if (!is_valid_frame_name(f.name) || !names.insert(f.name).second)
      throw ProtocolError(ErrorCode::kBadHeader, "encode: bad or duplicate frame name \"" + f.name + "\"");
    if (f.media_type.empty())
      throw ProtocolError(ErrorCode::kBadHeader, "encode: frame \"" + f.name + "\" has no media type");
    manifest.push_back({{"name", f.name}, {"media_type", f.media_type}, {"size", f.bytes.size()}});
  }
  header.erase("frames");
  if (!manifest.empty()) header["frames"] = std::move(manifest);
  // Same checks as the receiver, so that a bad message fails at its author.
  const auto type = check_type(header);
  check_request_id(header, type, Limits{});

  std::vector<std::string> wire;
  wire.reserve(message.frames.size() + 1);
  wire.push_back(header.dump());
  for (const auto& f : message.frames) wire.push_back(f.bytes);
  return wire;
}

Message decode(std::vector<std::string> wire, const Limits& limits) {
  check_header_size(wire, limits);
  Message message;
  message.header = parse_header(wire[0]);
  const auto request_id = readable_request_id(message.header);
  try {
    check_frame_sizes(wire, limits);
    check_version(message.header);
    const auto type = check_type(message.header);
    check_request_id(message.header, type, limits);
    const auto declared = parse_manifest(message.header, limits);
    match_frames(declared, wire);
    message.frames.reserve(declared.size());
    for (std::size_t i = 0; i < declared.size(); ++i)
      message.frames.push_back({declared[i].name, declared[i].media_type, std::move(wire[i + 1])});
  } catch (ProtocolError& e) {
    if (request_id && !e.request_id()) e.set_request_id(*request_id);
    throw;
  }
  return message;
}

Message decode_request(std::vector<std::string> wire, const Limits& limits) {
  Message m = decode(std::move(wire), limits);
  const auto type = m.type();
  if (kind_of(type) != MessageKind::kRequest)
    throw ProtocolError(ErrorCode::kUnknownType,
                        "\"" + std::string(to_string(type)) + "\" is not a request type",
                        m.request_id());
  return m;
}

}  // namespace brainshift::protocol
