#pragma once
// Reading brainshift's TOML configuration (config/brainshiftd.toml) into the
// engine's plain parameter structs. The server and the client's offline
// commands share this; the engine itself never parses configuration.
#include <filesystem>
#include <string>

#include "label_table_file.h"
#include "pipeline/pipeline_parameters.h"

namespace toml { inline namespace v3 { class table; } }

namespace brainshift::config {

// The default configuration shipped in config/brainshiftd.toml, compiled in so
// that a binary started anywhere has the same defaults.
const std::string& default_config_text();

// Parses the whole file; sections it does not know are left to their owners
// (e.g. [server] for brainshiftd). Unknown keys inside known sections are an
// InputError naming the key, so a typo never silently falls back to a default.
PipelineParameters pipeline_parameters_from_file(const std::filesystem::path& path);
PipelineParameters pipeline_parameters_from_text(const std::string& toml_text,
                                                 const std::string& source_name);
// The label table alone (label_table_from_text, default_label_table) is
// label_table_file.h, which needs no pipeline.

}  // namespace brainshift::config
