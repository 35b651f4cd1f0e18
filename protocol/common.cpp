#include "protocol/common.h"

#include "protocol/fields.h"

namespace brainshift::protocol {

nlohmann::json to_json_value(const MeshSize& mesh) {
  return {{"nodes", mesh.nodes}, {"tets", mesh.tets}};
}

MeshSize mesh_size_from_json(const nlohmann::json& j, const std::string& context) {
  const detail::FieldReader f(j, context);
  return {f.uint("nodes"), f.uint("tets")};
}

nlohmann::json to_json_value(const ErrorInfo& error) {
  return {{"code", std::string(to_string(error.code))}, {"message", error.message}};
}

ErrorInfo error_info_from_json(const nlohmann::json& j, const std::string& context) {
  const detail::FieldReader f(j, context);
  const auto code = error_code_from_string(f.string("code"));
  if (!code) f.fail("code", "is not a known error code");
  return {*code, f.text("message")};
}

void add_result_kind(nlohmann::json& object, const ResultKindInfo& result) {
  object["kind"] = std::string(to_string(result.kind));
  if (result.kind == ResultKind::affine_only_fallback) object["fallback_reason"] = result.fallback_reason;
  if (!result.caution.empty()) object["caution"] = result.caution;
}

std::optional<ResultKindInfo> result_kind_from_json(const nlohmann::json& object, const std::string& context) {
  const detail::FieldReader f(object, context);
  const auto text = f.opt_string("kind");
  if (!text) return std::nullopt;
  const auto kind = result_kind_from_string(*text);
  if (!kind) f.fail("kind", "must be \"nonrigid\" or \"affine_only_fallback\"");
  return ResultKindInfo{*kind, f.text("fallback_reason"), f.text("caution")};
}

}  // namespace brainshift::protocol
