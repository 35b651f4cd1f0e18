#pragma once
// Rank 0 of brainshiftd: the ZeroMQ sockets on a socket thread, the engine
// jobs on the calling (main) thread.
#include <atomic>
#include <filesystem>

#include "server/engine_port.h"
#include "server/server_settings.h"

namespace brainshift::server {

struct DaemonOptions {
  ServerSettings settings;
  // When set, {"endpoint","events","pid"} is written there (atomically) once
  // both sockets are bound: tests and scripts bind port 0 / "*" and read it.
  std::filesystem::path ready_file;
};

// Runs until stop is set (signal) or a shutdown request; returns the exit
// code. Always stops the MPI workers before returning.
int run_daemon(const DaemonOptions& options, EnginePort& engine, const std::atomic<bool>& stop);

}  // namespace brainshift::server
