#include "protocol/label_tables.h"

#include <algorithm>
#include <set>

#include <nlohmann/json.hpp>

#include "protocol/fields.h"
#include "protocol/message_parsing.h"
#include "protocol/result_outputs.h"

namespace brainshift::protocol {

using nlohmann::json;
using detail::expect_frames;
using detail::expect_type;
using detail::FieldReader;
using detail::with_request_id;

// ---- label map -------------------------------------------------------------

std::string make_label_map_json(const LabelMap& map) {
  json structures = json::object();
  for (const auto& [name, values] : map.structures) structures[name] = values;
  return json{{"v", 1}, {"structures", structures}}.dump(2);
}

LabelMap parse_label_map_json(std::string_view text) {
  if (text.size() > kMaxLabelTableBytes)
    throw ProtocolError(ErrorCode::kInvalidRequest, "label_table: " + std::to_string(text.size()) +
                                                        " bytes; a label table is at most " +
                                                        std::to_string(kMaxLabelTableBytes));
  // A label table is two levels deep; the bound keeps recursion in the JSON library shallow.
  if (json_nesting_depth(text) > Limits{}.max_header_depth)
    throw ProtocolError(ErrorCode::kInvalidRequest, "label_table: nested too deeply");
  const json j = json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded()) throw ProtocolError(ErrorCode::kInvalidRequest, "label_table: not valid JSON");
  const FieldReader f(j, "label_table");
  if (f.uint("v") != 1) f.fail("v", "must be 1");
  LabelMap table;
  if (f.object("structures").size() > kMaxStructures)
    f.fail("structures", "names more than " + std::to_string(kMaxStructures) + " structures");
  for (const auto& [name, values] : f.object("structures").items()) {
    if (!is_valid_structure_name(name))
      f.fail("structures", "\"" + name + "\" is not a structure name (1..64 of a-z, 0-9, _; a letter first)");
    if (!values.is_array() || values.empty()) f.fail("structures", "\"" + name + "\" needs a non-empty array");
    for (const auto& v : values) {
      if (!v.is_number_unsigned() || v.get<std::uint64_t>() == 0 || v.get<std::uint64_t>() > 65535)
        f.fail("structures", "\"" + name + "\" values must be label values in 1..65535");
      table.structures[name].push_back(v.get<std::uint16_t>());
    }
  }
  if (table.structures.empty()) f.fail("structures", "must name at least one structure");
  return table;
}

// ---- labels.get ------------------------------------------------------------

std::string colour_to_hex(const Rgb& colour) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string out = "#";
  for (std::uint8_t c : colour) {
    out.push_back(kDigits[c >> 4]);
    out.push_back(kDigits[c & 15]);
  }
  return out;
}

std::optional<Rgb> colour_from_hex(std::string_view text) {
  auto hex = [](char c) -> int {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
  };
  if (text.size() != 7 || text[0] != '#') return std::nullopt;
  Rgb out{};
  for (std::size_t c = 0; c < 3; ++c) {
    const int hi = hex(text[1 + 2 * c]), lo = hex(text[2 + 2 * c]);
    if (hi < 0 || lo < 0) return std::nullopt;
    out[c] = static_cast<std::uint8_t>(16 * hi + lo);
  }
  return out;
}

Message make_labels_request(const std::string& request_id) {
  return make_message(MessageType::kLabelsGet, request_id);
}

void parse_labels_request(const Message& m) {
  expect_type(m, MessageType::kLabelsGet);
  with_request_id(m, [&] { expect_frames(m, {}); });
}

Message make_labels_reply(const std::string& request_id, const LabelsReply& r) {
  Message m = make_message(MessageType::kLabelsGetReply, request_id);
  json labels = json::array();
  for (const auto& l : r.labels)
    labels.push_back({{"value", l.value}, {"name", l.name}, {"short_name", l.short_name}, {"role", l.role},
                      {"colour", colour_to_hex(l.colour)}, {"model", l.model}});
  m.header["labels"] = std::move(labels);
  return m;
}

LabelsReply parse_labels_reply(const Message& m) {
  expect_type(m, MessageType::kLabelsGetReply);
  return with_request_id(m, [&] {
    expect_frames(m, {});
    const FieldReader f(m.header, "labels.get.reply");
    const json& items = f.array("labels");
    if (items.empty() || items.size() > kMaxStructures)
      f.fail("labels", "must hold 1.." + std::to_string(kMaxStructures) + " labels");
    LabelsReply r;
    std::set<std::uint16_t> values;
    std::set<std::string> names;
    int parenchyma = 0;
    for (const auto& item : items) {
      const FieldReader l(item, "labels.get.reply.labels[]");
      LabelInfo info;
      const std::uint64_t value = l.uint("value");
      if (value < 1 || value > 65535) l.fail("value", "must lie in 1..65535");
      info.value = static_cast<std::uint16_t>(value);
      info.name = l.string("name");
      if (!is_valid_structure_name(info.name))
        l.fail("name", "\"" + info.name + "\" is not a structure name (1..64 of a-z, 0-9, _; a letter first)");
      info.short_name = l.string("short_name");
      if (info.short_name.size() > 11 || !is_valid_structure_name(info.short_name))
        l.fail("short_name", "\"" + info.short_name + "\" is not 1..11 of a-z, 0-9, _ (a letter first)");
      info.role = l.string("role");
      if (std::find(kLabelRoleNames.begin(), kLabelRoleNames.end(), info.role) == kLabelRoleNames.end())
        l.fail("role", "\"" + info.role + "\" is not parenchyma, cavity or structure");
      const auto colour = colour_from_hex(l.string("colour"));
      if (!colour) l.fail("colour", "is not of the form \"#rrggbb\"");
      info.colour = *colour;
      info.model = l.boolean("model", true);
      if (!values.insert(info.value).second) l.fail("value", std::to_string(value) + " is given twice");
      if (!names.insert(info.name).second) l.fail("name", "\"" + info.name + "\" is given twice");
      parenchyma += info.role == kLabelRoleNames[0];
      r.labels.push_back(std::move(info));
    }
    if (parenchyma != 1) f.fail("labels", "exactly one label must have role \"parenchyma\"");
    return r;
  });
}

}  // namespace brainshift::protocol
