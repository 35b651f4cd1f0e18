#pragma once
// The commands of `brainshift` that talk to brainshiftd: status, load-preop,
// push, pull, list, watch, shutdown.
#include <CLI/CLI.hpp>

namespace brainshift::cli {

struct NetworkOptions {
  std::string server = "tcp://127.0.0.1:5555";
  std::string events = "tcp://127.0.0.1:5556";
  double timeout_s = 10.0;  // per request
};

void add_network_commands(CLI::App& app, NetworkOptions& options, int* exit_code);

}  // namespace brainshift::cli
