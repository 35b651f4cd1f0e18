#pragma once
// The label table on the wire, both ways: the map from a sender's label
// values to the daemon's structures (the "label_table" frame of preop.load,
// PROTOCOL.md 5.2) and the daemon's own table as labels.get serves it
// (PROTOCOL.md 5.6). The engine's type is brainshift::LabelTable
// (engine/core/label_table.h).
#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "protocol/message.h"

namespace brainshift::protocol {

// ---- Label map (the optional "label_table" frame of preop.load) -----------

// Bounds on what a client sends (PROTOCOL.md section 13.5).
inline constexpr std::size_t kMaxLabelTableBytes = 64 * 1024;
// Structures named in a label table or a scan.result request.
inline constexpr std::size_t kMaxStructures = 64;

// Which label values of the preop label image make up each structure, e.g.
// JHU labels 7 and 8 both belong to the corticospinal tract. Structure names
// are those of the daemon's label table (config/labels.toml); the daemon, not
// the codec, checks them against it.
// A map from the sender's values to the daemon's label table (whose type is
// brainshift::LabelTable, engine/core/label_table.h); on the wire it is the
// frame "label_table" (PROTOCOL.md 5.2).
struct LabelMap {
  std::map<std::string, std::vector<std::uint16_t>> structures{};
  bool operator==(const LabelMap&) const = default;
};
std::string make_label_map_json(const LabelMap& map);
LabelMap parse_label_map_json(std::string_view text);

// ---- labels.get: the daemon's label table --------------------------------

// How the daemon's label table names, colours and models its labels, as
// labels.get.reply serves it (PROTOCOL.md 5.6), so that a viewer (the Slicer
// scene of `brainshift pull --scene`) needs no copy of the daemon's
// labels.toml. The engine's type is brainshift::LabelTable
// (engine/core/label_table.h); its role names and "#rrggbb" colours are
// spelled here, once, for both.
inline constexpr std::array<std::string_view, 3> kLabelRoleNames{"parenchyma", "cavity", "structure"};
using Rgb = std::array<std::uint8_t, 3>;
std::string colour_to_hex(const Rgb& colour);                    // "#rrggbb", lower case
std::optional<Rgb> colour_from_hex(std::string_view text);  // nullopt unless "#rrggbb"

struct LabelInfo {
  std::uint16_t value = 0;  // 1..65535, the label value in warped_labels
  std::string name{};       // structure name (model.<name>, models/<name>.vtp)
  std::string short_name{}; // at most 11 characters (OpenIGTLink device names)
  std::string role{};       // one of kLabelRoleNames; exactly one "parenchyma"
  Rgb colour{};
  bool model = true;        // the daemon makes a surface model of it
  bool operator==(const LabelInfo&) const = default;
};
struct LabelsReply {
  std::vector<LabelInfo> labels{};  // 1..kMaxStructures, values and names unique
  bool operator==(const LabelsReply&) const = default;
};
Message make_labels_request(const std::string& request_id);
void parse_labels_request(const Message& m);
Message make_labels_reply(const std::string& request_id, const LabelsReply& r);
LabelsReply parse_labels_reply(const Message& m);

}  // namespace brainshift::protocol
