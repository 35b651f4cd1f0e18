#include "server/preop_labels.h"

#include <array>
#include <fstream>
#include <sstream>

#include "core/errors.h"
#include "core/labels.h"

namespace brainshift::server {

std::uint16_t engine_label_of(protocol::Structure s) {
  switch (s) {
    case protocol::Structure::kBrain: return labels::brain;
    case protocol::Structure::kVentricles: return labels::ventricles;
    case protocol::Structure::kCorticospinalTract: return labels::corticospinal_tract;
    case protocol::Structure::kTumor: return labels::tumor;
  }
  return 0;
}

void remap_preop_labels(LabelImage& labels, const protocol::LabelTable* table) {
  std::array<std::uint16_t, 65536> map{};  // 0 = unlisted
  std::array<bool, 65536> listed{};
  listed[0] = true;
  if (table) {
    for (const auto& [structure, values] : table->structures)
      for (std::uint16_t v : values) {
        map[v] = engine_label_of(structure);
        listed[v] = true;
      }
  } else {
    for (std::uint16_t v = 1; v <= 4; ++v) {
      map[v] = v;
      listed[v] = true;
    }
  }
  std::size_t brain = 0;
  for (auto& v : labels.voxels) {
    if (!listed[v])
      throw InputError("labels: value " + std::to_string(v) +
                       (table ? " is not in the label table" : " is not a default label (1..4); send a label table"));
    v = map[v];
    brain += v == 1;
  }
  if (brain == 0) throw InputError("labels: no brain voxel (label 1 after mapping)");
}

std::string read_text_file(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path.string() + ": cannot open");
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

}  // namespace brainshift::server
