#pragma once
// Label values as the engine's label table has them, whatever values the
// sender's atlas uses: the preop labels of preop.load, and the intraop labels
// of every scan pushed against that preop (PROTOCOL.md: the same values);
// and the table itself as labels.get serves it.
#include <string>

#include "core/image.h"
#include "core/label_table.h"
#include "protocol/requests.h"

namespace brainshift::server {

// With a label map (the preop.load label_table frame): every structure it
// names must be in the engine's table, every non-zero voxel value must be
// listed, and each becomes its structure's value in the table. Without one,
// the values must already be the table's. InputError naming the first
// offending structure or value, and when no voxel is the parenchyma label.
void map_label_values(LabelImage& labels, const protocol::LabelMap* map, const LabelTable& table);

// The table as labels.get.reply serves it (names, roles, colours, models).
protocol::LabelsReply served_labels(const LabelTable& table);

}  // namespace brainshift::server
