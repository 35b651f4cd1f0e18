#pragma once
// Every message type on the wire, with its exact string name. The string is
// what travels in the header's "type" field and, for events, the PUB topic.
#include <optional>
#include <string_view>

namespace brainshift::protocol {

enum class MessageType {
  // Requests (client -> ROUTER).
  kStatus,
  kPreopLoad,
  kScanPush,
  kScanResult,
  kScanList,
  kLabelsGet,
  kShutdown,
  // Replies (ROUTER -> client), one per request, echoing its request_id.
  kStatusReply,
  kPreopLoadReply,
  kScanPushReply,
  kScanResultReply,
  kScanListReply,
  kLabelsGetReply,
  kShutdownReply,
  kError,
  // Events (PUB), no reply.
  kEventPreopProgress,
  kEventPreopReady,
  kEventPreopFailed,
  kEventStage,
  kEventScanProgress,
  kEventScanDone,
  kEventScanFailed,
  kEventServerShutdown,
};

enum class MessageKind { kRequest, kReply, kEvent };

std::string_view to_string(MessageType type);
// nullopt for a name this protocol version does not know.
std::optional<MessageType> message_type_from_string(std::string_view name);
MessageKind kind_of(MessageType type);
// The reply type a successful request gets (kError is always possible too).
// Throws std::invalid_argument for a type that is not a request.
MessageType reply_type_for(MessageType request);

}  // namespace brainshift::protocol
