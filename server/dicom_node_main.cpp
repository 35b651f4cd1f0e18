// brainshift-dicom-node: the scanner's DICOM node ([dicom_node] of
// brainshiftd.toml), a sidecar of brainshiftd (server/dicom_node.h).
#include <atomic>
#include <csignal>
#include <iostream>

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include "server/dicom_node.h"

namespace {
std::atomic<bool> g_stop{false};
static_assert(std::atomic<bool>::is_always_lock_free, "the signal handler needs a lock-free flag");
extern "C" void on_signal(int) { g_stop = true; }
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"brainshift-dicom-node: receives series from the scanner (C-STORE) and queues them"};
  std::string config;
  app.add_option("--config", config, "brainshiftd.toml with a [dicom_node] table")->required();
  CLI11_PARSE(app, argc, argv);
  try {
    const auto settings = brainshift::server::dicom_node_settings_from_file(config);
    if (!settings.enabled) {
      std::cerr << "brainshift-dicom-node: [dicom_node] enabled = false in " << config << "\n";
      return 2;
    }
    struct sigaction sa {};
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, nullptr);
    sigaction(SIGTERM, &sa, nullptr);
    brainshift::server::run_dicom_node(settings, [] { return g_stop.load(); });
  } catch (const std::exception& e) {
    std::cerr << "brainshift-dicom-node: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
