#pragma once
// Preop label values as the engine expects them (1 brain, 2 ventricles,
// 3 corticospinal tract, 4 tumor), whatever values the sender's atlas uses.
#include <filesystem>
#include <string>

#include "core/image.h"
#include "protocol/requests.h"

namespace brainshift::server {

// Engine label value of each protocol structure.
std::uint16_t engine_label_of(protocol::Structure s);

// With a table: every non-zero value must be listed (InputError naming the
// first unlisted value) and is replaced by its structure's engine value.
// Without: values must already be engine values (0..4). Also InputError when
// no voxel is brain.
void remap_preop_labels(LabelImage& labels, const protocol::LabelTable* table);

// Whole file as bytes; InputError naming the path when unreadable.
std::string read_text_file(const std::filesystem::path& path);

}  // namespace brainshift::server
