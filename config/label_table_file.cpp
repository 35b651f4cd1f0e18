#include "label_table_file.h"

#include "config/toml_reader.h"
#include "core/errors.h"
#include "embedded_defaults.h"

namespace brainshift::config {

LabelTable label_table_from_document(TomlSection& root) {
  std::vector<TomlSection> entries = root.tables("label");
  if (entries.empty()) root.fail("label", "at least one [[label]] entry is required");
  LabelTable table;
  for (TomlSection& s : entries) {
    LabelEntry e;
    const std::int64_t value = s.integer("value", -1, 1, 65535);
    if (value < 0) s.fail("value", "required, in [1, 65535]");
    s.read("name", e.name);
    s.read("short_name", e.short_name);
    const std::string role = s.string("role", "structure");
    s.read("youngs_modulus_pa", e.youngs_modulus_pa);
    s.read("poisson_ratio", e.poisson_ratio);
    s.read("model", e.make_model);
    s.read("resectable", e.resectable);
    const std::string colour = s.string("colour", "");
    s.reject_unknown_keys();
    e.value = static_cast<std::uint16_t>(value);
    try {
      e.colour = colour.empty() ? default_label_colour(e.value) : label_colour_from_hex(colour);
    } catch (const InputError& err) {
      s.fail("colour", e.name + ": " + err.what());
    }
    e.role = label_role_from_string(role);
    table.entries.push_back(e);
  }
  table.validate();
  return table;
}

LabelTable label_table_from_text(const std::string& toml_text, const std::string& source_name) {
  const toml::table document = parse_toml(toml_text, source_name);
  TomlSection root(&document, source_name, "");
  return label_table_from_document(root);
}

const LabelTable& default_label_table() {
  static const LabelTable table = label_table_from_text(embedded_labels_toml(), "built-in labels.toml");
  return table;
}

}  // namespace brainshift::config
