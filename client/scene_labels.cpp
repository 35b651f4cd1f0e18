#include "scene_labels.h"

#include <fstream>
#include <sstream>

#include "config_file.h"
#include "connection.h"
#include "core/errors.h"
#include "exit_codes.h"

namespace brainshift::cli {

std::vector<SceneLabel> scene_labels_from_toml(const std::string& toml_file) {
  try {
    LabelTable table;
    if (toml_file.empty()) {
      table = config::pipeline_parameters_from_text(config::default_config_text(), "built-in").label_table;
    } else {
      std::ifstream in(toml_file, std::ios::binary);
      if (!in) throw InputError(toml_file + ": cannot be read");
      std::ostringstream text;
      text << in.rdbuf();
      table = config::label_table_from_text(text.str(), toml_file);
    }
    std::vector<SceneLabel> out;
    for (const auto& e : table.entries) out.push_back({e.value, e.name, e.colour, e.role == LabelRole::parenchyma});
    return out;
  } catch (const InputError& e) {
    throw CommandError(kExitUsage, e.what());
  }
}

}  // namespace brainshift::cli
