#include "core/label_table.h"

#include <set>

#include "core/errors.h"
#include "protocol/requests.h"
#include "protocol/result_outputs.h"
#include "core/label_colour.h"

namespace brainshift {

const LabelEntry* LabelTable::find(std::uint16_t value) const {
  for (const auto& e : entries)
    if (e.value == value) return &e;
  return nullptr;
}

const LabelEntry* LabelTable::find(const std::string& name) const {
  for (const auto& e : entries)
    if (e.name == name) return &e;
  return nullptr;
}

std::uint16_t LabelTable::brain_label() const {
  for (const auto& e : entries)
    if (e.role == LabelRole::parenchyma) return e.value;
  throw InputError("label table: no label has role \"parenchyma\"");
}

std::vector<std::uint16_t> LabelTable::cavity_labels() const {
  std::vector<std::uint16_t> out;
  for (const auto& e : entries)
    if (e.role == LabelRole::cavity) out.push_back(e.value);
  return out;
}

std::vector<std::uint16_t> LabelTable::resectable_labels() const {
  std::vector<std::uint16_t> out;
  for (const auto& e : entries)
    if (e.resectable) out.push_back(e.value);
  return out;
}

std::string short_name_of(const LabelEntry& entry) {
  return entry.short_name.empty() ? entry.name.substr(0, kMaxShortNameLength) : entry.short_name;
}

void LabelTable::validate() const {
  std::set<std::uint16_t> values;
  std::set<std::string> names, short_names;
  if (entries.empty()) throw InputError("label table: no entries (the shipped one is config/labels.toml)");
  if (entries.size() > protocol::kMaxStructures)
    throw InputError("label table: " + std::to_string(entries.size()) + " labels; at most " +
                     std::to_string(protocol::kMaxStructures) + " (a label map and labels.get name at most that many)");
  int parenchyma = 0;
  for (const auto& e : entries) {
    const std::string where = "label table entry " + std::to_string(e.value) + " (\"" + e.name + "\")";
    if (e.value == 0) throw InputError(where + ": value 0 is reserved for background");
    if (e.name.empty()) throw InputError(where + ": empty name");
    if (!protocol::is_valid_structure_name(e.name))
      throw InputError(where + ": a name is 1..64 of a-z, 0-9 and _, starting with a letter");
    const bool short_ok = e.short_name.empty() || (e.short_name.size() <= kMaxShortNameLength &&
                                                   protocol::is_valid_structure_name(e.short_name));
    if (!short_ok)
      throw InputError(where + ": short_name is 1..11 of a-z, 0-9 and _, starting with a letter");
    if (!short_names.insert(short_name_of(e)).second)
      throw InputError(where + ": short name \"" + short_name_of(e) + "\" is another label's too");
    if (!values.insert(e.value).second) throw InputError(where + ": duplicate value");
    if (!names.insert(e.name).second) throw InputError(where + ": duplicate name");
    if (!(e.youngs_modulus_pa > 0.0)) throw InputError(where + ": youngs_modulus_pa must be > 0");
    if (!(e.poisson_ratio > 0.0 && e.poisson_ratio < 0.5))
      throw InputError(where + ": poisson_ratio must lie in (0, 0.5)");
    if (e.resectable && e.role != LabelRole::structure)
      throw InputError(where + ": only a \"structure\" label can be resectable");
    if (e.role == LabelRole::parenchyma) ++parenchyma;
  }
  if (parenchyma != 1)
    throw InputError("label table: exactly one label must have role \"parenchyma\" (found " +
                     std::to_string(parenchyma) + ")");
}

std::string to_string(LabelRole role) {
  return std::string(protocol::kLabelRoleNames.at(static_cast<std::size_t>(role)));
}

LabelColour label_colour_from_hex(const std::string& text) {
  const auto colour = protocol::colour_from_hex(text);
  if (!colour) throw InputError("colour \"" + text + "\" is not of the form \"#rrggbb\"");
  return *colour;
}

std::string to_hex(const LabelColour& colour) { return protocol::colour_to_hex(colour); }

LabelColour default_label_colour(std::uint16_t value) {
  // Distinct, saturated hues that read on a grey MR slice and differ from the
  // shipped table's green, cyan, red and yellow.
  static constexpr std::array<LabelColour, 6> palette{{
      {255, 0, 255}, {255, 140, 0}, {150, 90, 255}, {0, 255, 170}, {255, 105, 180}, {170, 255, 0}}};
  return palette[value % palette.size()];
}

LabelRole label_role_from_string(const std::string& text) {
  for (std::size_t i = 0; i < protocol::kLabelRoleNames.size(); ++i)
    if (protocol::kLabelRoleNames[i] == text) return static_cast<LabelRole>(i);
  throw InputError("unknown label role \"" + text + "\" (expected parenchyma, cavity or structure)");
}

}  // namespace brainshift
