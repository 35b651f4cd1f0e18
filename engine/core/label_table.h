#pragma once
// The label table: what each preop label value means for the pipeline.
// Plain data; parsed from config/labels.toml (or a protocol message) at the edges.
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "core/label_colour.h"

namespace brainshift {

// In the order of their names, protocol::kLabelRoleNames (protocol/requests.h).
enum class LabelRole {
  parenchyma,  // meshed tissue (the brain label)
  cavity,      // meshed as a hole whose wall is matched (lateral ventricles)
  structure,   // carried inside the tissue (tract, tumor): own material, own model
};

struct LabelEntry {
  std::uint16_t value = 0;
  std::string name;  // model name, e.g. "corticospinal_tract": 1..64 of [a-z0-9_], a letter first
  // At most 11 characters: the name in OpenIGTLink device names
  // ("bs.model.cst"), whose header field holds 20 bytes. Empty: the name,
  // cut to 11 characters.
  std::string short_name;
  LabelRole role = LabelRole::structure;
  double youngs_modulus_pa = 3000.0;
  double poisson_ratio = 0.35;
  bool make_model = true;  // write a surface model of this label
  // May be removed during surgery (the tumor). Meshed as its own subdomain and
  // given a second warm system in which its wall is fixed, so that a
  // resection cavity in an intraop scan can pull the wall (structure role only).
  bool resectable = false;
  // How the structure is drawn wherever it is shown: the report's contours and
  // legend, the Slicer scene's models and its label colour table.
  LabelColour colour = {255, 0, 255};
};

struct LabelTable {
  std::vector<LabelEntry> entries;

  // No defaults here: the shipped table is config/labels.toml, compiled into
  // every binary by config/ (one copy; config::default_label_table()).
  const LabelEntry* find(std::uint16_t value) const;
  const LabelEntry* find(const std::string& name) const;
  // The parenchyma label (exactly one) and the cavity labels.
  std::uint16_t brain_label() const;
  std::vector<std::uint16_t> cavity_labels() const;
  std::vector<std::uint16_t> resectable_labels() const;
  // Throws InputError: duplicate values, names or short names, value 0, a
  // name that is not [a-z][a-z0-9_]{0,63} (it becomes file and frame names),
  // a short name over 11 characters, no or several parenchyma labels, nu
  // outside (0, 0.5), E <= 0, more labels than the protocol can name
  // (protocol::kMaxStructures, 64).
  void validate() const;
};

// The entry's short name, or its name cut to 11 characters.
std::string short_name_of(const LabelEntry& entry);
inline constexpr std::size_t kMaxShortNameLength = 11;

std::string to_string(LabelRole role);
// "#rrggbb" (as written in labels.toml); InputError naming the text otherwise.
LabelColour label_colour_from_hex(const std::string& text);
std::string to_hex(const LabelColour& colour);
// The colour of a label whose table entry names none: a fixed palette by value,
// so an unlisted fifth structure still gets a colour of its own.
LabelColour default_label_colour(std::uint16_t value);
LabelRole label_role_from_string(const std::string& text);  // InputError if unknown

}  // namespace brainshift
