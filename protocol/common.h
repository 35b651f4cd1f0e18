#pragma once
// Small value types shared by replies, events and the timings JSON.
#include <cstdint>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "protocol/error_codes.h"
#include "protocol/result_kind.h"

namespace brainshift::protocol {

struct MeshSize {
  std::uint64_t nodes = 0;
  std::uint64_t tets = 0;
  bool operator==(const MeshSize&) const = default;
};

// A typed error inside a reply or event body: {"code": "...", "message": "..."}.
struct ErrorInfo {
  ErrorCode code = ErrorCode::kInternal;
  std::string message{};
  bool operator==(const ErrorInfo&) const = default;
};

// A done scan's result kind and, for the fallback, why (PROTOCOL.md 5.4):
// the fields "kind" and "fallback_reason" of event.scan.done,
// scan.result.reply and scan.list.reply. Servers before revision 2 of
// version 1 (PROTOCOL.md 10) leave them out.
struct ResultKindInfo {
  ResultKind kind = ResultKind::nonrigid;
  std::string fallback_reason{};  // "" for nonrigid
  // A non-rigid result to be read with care, and why ("caution", revision 6):
  // e.g. given labels the image's refinement changed grossly. "" for none.
  std::string caution{};
  bool operator==(const ResultKindInfo&) const = default;
};

nlohmann::json to_json_value(const MeshSize& mesh);
MeshSize mesh_size_from_json(const nlohmann::json& j, const std::string& context);
nlohmann::json to_json_value(const ErrorInfo& error);
ErrorInfo error_info_from_json(const nlohmann::json& j, const std::string& context);
// Adds "kind" (and "fallback_reason" for the fallback, "caution" when there
// is one) to a header or object.
void add_result_kind(nlohmann::json& object, const ResultKindInfo& result);
// nullopt when "kind" is absent; throws ProtocolError(kInvalidRequest) for an
// unknown kind.
std::optional<ResultKindInfo> result_kind_from_json(const nlohmann::json& object, const std::string& context);

}  // namespace brainshift::protocol
