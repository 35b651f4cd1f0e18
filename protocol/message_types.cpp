#include "protocol/message_types.h"

#include <array>
#include <stdexcept>
#include <string>
#include <utility>

namespace brainshift::protocol {
namespace {

constexpr std::array<std::pair<MessageType, std::string_view>, 23> kNames{{
    {MessageType::kStatus, "status"},
    {MessageType::kPreopLoad, "preop.load"},
    {MessageType::kScanPush, "scan.push"},
    {MessageType::kScanResult, "scan.result"},
    {MessageType::kScanList, "scan.list"},
    {MessageType::kLabelsGet, "labels.get"},
    {MessageType::kShutdown, "shutdown"},
    {MessageType::kStatusReply, "status.reply"},
    {MessageType::kPreopLoadReply, "preop.load.reply"},
    {MessageType::kScanPushReply, "scan.push.reply"},
    {MessageType::kScanResultReply, "scan.result.reply"},
    {MessageType::kScanListReply, "scan.list.reply"},
    {MessageType::kLabelsGetReply, "labels.get.reply"},
    {MessageType::kShutdownReply, "shutdown.reply"},
    {MessageType::kError, "error"},
    {MessageType::kEventPreopProgress, "event.preop.progress"},
    {MessageType::kEventPreopReady, "event.preop.ready"},
    {MessageType::kEventPreopFailed, "event.preop.failed"},
    {MessageType::kEventStage, "event.stage"},
    {MessageType::kEventScanProgress, "event.scan.progress"},
    {MessageType::kEventScanDone, "event.scan.done"},
    {MessageType::kEventScanFailed, "event.scan.failed"},
    {MessageType::kEventServerShutdown, "event.server.shutdown"},
}};

}  // namespace

std::string_view to_string(MessageType type) {
  for (const auto& [t, name] : kNames)
    if (t == type) return name;
  throw std::logic_error("message type without a name: " +
                         std::to_string(static_cast<int>(type)));
}

std::optional<MessageType> message_type_from_string(std::string_view name) {
  for (const auto& [t, n] : kNames)
    if (n == name) return t;
  return std::nullopt;
}

MessageKind kind_of(MessageType type) {
  if (type <= MessageType::kShutdown) return MessageKind::kRequest;
  if (type <= MessageType::kError) return MessageKind::kReply;
  return MessageKind::kEvent;
}

MessageType reply_type_for(MessageType request) {
  switch (request) {
    case MessageType::kStatus: return MessageType::kStatusReply;
    case MessageType::kPreopLoad: return MessageType::kPreopLoadReply;
    case MessageType::kScanPush: return MessageType::kScanPushReply;
    case MessageType::kScanResult: return MessageType::kScanResultReply;
    case MessageType::kScanList: return MessageType::kScanListReply;
    case MessageType::kLabelsGet: return MessageType::kLabelsGetReply;
    case MessageType::kShutdown: return MessageType::kShutdownReply;
    default:
      throw std::invalid_argument("reply_type_for: " + std::string(to_string(request)) +
                                  " is not a request");
  }
}

}  // namespace brainshift::protocol
