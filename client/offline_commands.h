#pragma once
// Commands of the `brainshift` CLI that run the engine in this process, with
// no daemon: `register` (the one-shot registration) and `phantom`.
#include <CLI/CLI.hpp>

namespace brainshift::cli {

// Adds the offline subcommands to the CLI. Each sets *exit_code when it runs.
void add_offline_commands(CLI::App& app, int* exit_code);

}  // namespace brainshift::cli
