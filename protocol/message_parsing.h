#pragma once
// What every typed parser of a message checks first (requests.cpp,
// label_tables.cpp): its type, the frames it may carry, and the request id
// on any error found in its fields. Internal to the protocol library.
#include <algorithm>
#include <initializer_list>
#include <string>
#include <string_view>

#include "protocol/error_codes.h"
#include "protocol/message.h"
#include "protocol/message_types.h"
#include "protocol/requests.h"  // throw_if_error

namespace brainshift::protocol::detail {

inline std::string context_of(const Message& m) { return std::string(to_string(m.type())); }

// Replies: an error reply is rethrown as the ProtocolError it describes, so a
// client can call parse_*_reply directly on whatever came back.
inline void expect_type(const Message& m, MessageType expected) {
  if (kind_of(expected) == MessageKind::kReply) throw_if_error(m);
  const auto actual = m.type();
  if (actual != expected)
    throw ProtocolError(ErrorCode::kInvalidRequest,
                        "expected a " + std::string(to_string(expected)) + " message, got " +
                            std::string(to_string(actual)),
                        m.request_id());
}

// "Extra frames" are refused by name: each type lists the frames it may carry.
inline void expect_frames(const Message& m, std::initializer_list<std::string_view> allowed) {
  for (const auto& f : m.frames)
    if (std::find(allowed.begin(), allowed.end(), f.name) == allowed.end())
      throw ProtocolError(ErrorCode::kInvalidRequest,
                          context_of(m) + ": unexpected frame \"" + f.name + "\"", m.request_id());
}

// Attaches the request id to any field error found while parsing m.
template <class Fn>
auto with_request_id(const Message& m, Fn fn) {
  try {
    return fn();
  } catch (ProtocolError& e) {
    if (!e.request_id()) e.set_request_id(m.request_id());
    throw;
  }
}

}  // namespace brainshift::protocol::detail
