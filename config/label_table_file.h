#pragma once
// Reading a label table (config/labels.toml, or the [[label]] entries of a
// brainshiftd.toml) into the engine's LabelTable. Needs only toml++ and the
// label table's library, not the pipeline: the daemon's core, its tests and
// the OpenIGTLink tools link this without the engine's solvers.
#include <string>

#include "core/label_table.h"

namespace brainshift::config {

class TomlSection;

// A label table alone, e.g. config/labels.toml or a site's own.
LabelTable label_table_from_text(const std::string& toml_text, const std::string& source_name);
// The [[label]] entries of a document (at least one), validated.
LabelTable label_table_from_document(TomlSection& root);
// config/labels.toml as shipped (compiled in): the one copy of the default
// labels (1 brain, 2 ventricles, 3 corticospinal tract, 4 tumor).
const LabelTable& default_label_table();

}  // namespace brainshift::config
