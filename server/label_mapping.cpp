#include "server/label_mapping.h"

#include <array>

#include "core/errors.h"

namespace brainshift::server {
namespace {

std::string names_of(const LabelTable& table) {
  std::string out;
  for (const auto& e : table.entries) out += (out.empty() ? "" : ", ") + e.name;
  return out;
}

std::string values_of(const LabelTable& table) {
  std::string out;
  for (const auto& e : table.entries) out += (out.empty() ? "" : ", ") + std::to_string(e.value);
  return out;
}

}  // namespace

void map_label_values(LabelImage& labels, const protocol::LabelMap* map, const LabelTable& table) {
  std::array<std::uint16_t, 65536> to{};  // 0 = unlisted
  std::array<bool, 65536> listed{};
  listed[0] = true;
  if (map) {
    for (const auto& [name, values] : map->structures) {
      const LabelEntry* entry = table.find(name);
      if (!entry)
        throw InputError("label_table: structure \"" + name + "\" is not in the daemon's label table (" +
                         names_of(table) + ")");
      for (std::uint16_t v : values) {
        if (listed[v] && to[v] != entry->value)
          throw InputError("label_table: value " + std::to_string(v) + " is given to two structures");
        to[v] = entry->value;
        listed[v] = true;
      }
    }
  } else {
    for (const auto& e : table.entries) {
      to[e.value] = e.value;
      listed[e.value] = true;
    }
  }
  const std::uint16_t parenchyma = table.brain_label();
  std::size_t parenchyma_voxels = 0;
  for (auto& v : labels.voxels) {
    if (!listed[v])
      throw InputError("labels: value " + std::to_string(v) +
                       (map ? " is not in the label table"
                            : " is not a value of the daemon's label table (" + values_of(table) +
                                  "); send a label table"));
    v = to[v];
    parenchyma_voxels += v == parenchyma;
  }
  if (parenchyma_voxels == 0)
    throw InputError("labels: no " + table.find(parenchyma)->name + " voxel (label " + std::to_string(parenchyma) +
                     " after mapping)");
}

protocol::LabelsReply served_labels(const LabelTable& table) {
  protocol::LabelsReply reply;
  for (const LabelEntry& e : table.entries)
    reply.labels.push_back({e.value, e.name, short_name_of(e), to_string(e.role), e.colour, e.make_model});
  return reply;
}

}  // namespace brainshift::server
