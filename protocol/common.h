#pragma once
// Small value types shared by replies, events and the timings JSON.
#include <cstdint>
#include <string>

#include <nlohmann/json.hpp>

#include "protocol/error_codes.h"

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

nlohmann::json to_json_value(const MeshSize& mesh);
MeshSize mesh_size_from_json(const nlohmann::json& j, const std::string& context);
nlohmann::json to_json_value(const ErrorInfo& error);
ErrorInfo error_info_from_json(const nlohmann::json& j, const std::string& context);

}  // namespace brainshift::protocol
