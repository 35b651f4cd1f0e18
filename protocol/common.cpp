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

}  // namespace brainshift::protocol
