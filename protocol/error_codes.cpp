#include "protocol/error_codes.h"

#include <array>
#include <string>
#include <utility>

namespace brainshift::protocol {
namespace {

constexpr std::array<std::pair<ErrorCode, std::string_view>, 15> kNames{{
    {ErrorCode::kMalformedJson, "malformed_json"},
    {ErrorCode::kVersionMismatch, "version_mismatch"},
    {ErrorCode::kUnknownType, "unknown_type"},
    {ErrorCode::kBadHeader, "bad_header"},
    {ErrorCode::kFrameCountMismatch, "frame_count_mismatch"},
    {ErrorCode::kFrameSizeMismatch, "frame_size_mismatch"},
    {ErrorCode::kTooLarge, "too_large"},
    {ErrorCode::kInvalidRequest, "invalid_request"},
    {ErrorCode::kBusy, "busy"},
    {ErrorCode::kNotFound, "not_found"},
    {ErrorCode::kNotReady, "not_ready"},
    {ErrorCode::kScanFailed, "scan_failed"},
    {ErrorCode::kConflict, "conflict"},
    {ErrorCode::kUnauthorised, "unauthorised"},
    {ErrorCode::kInternal, "internal"},
}};

}  // namespace

std::string_view to_string(ErrorCode code) {
  for (const auto& [c, name] : kNames)
    if (c == code) return name;
  throw std::logic_error("error code without a name: " + std::to_string(static_cast<int>(code)));
}

std::optional<ErrorCode> error_code_from_string(std::string_view name) {
  for (const auto& [c, n] : kNames)
    if (n == name) return c;
  return std::nullopt;
}

bool is_retryable(ErrorCode code) {
  return code == ErrorCode::kBusy || code == ErrorCode::kNotReady || code == ErrorCode::kInternal;
}

}  // namespace brainshift::protocol
