// brainshiftd: the operating-room registration daemon.
//
// One process, or every rank of `mpirun -np N`: rank 0 owns the sockets, the
// store and the protocol; ranks > 0 only serve the engine's collective steps
// (run_worker_loop) and never touch sockets.
#include <malloc.h>
#include <mpi.h>

#include <atomic>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include "config/config_file.h"
#include "core/errors.h"
#include "fem/petsc_session.h"
#include "server/case_store.h"
#include "server/daemon.h"
#include "server/engine_adapter.h"

namespace {

std::atomic<bool> g_stop{false};
static_assert(std::atomic<bool>::is_always_lock_free, "the signal handler needs a lock-free flag");

extern "C" void on_signal(int) { g_stop = true; }

void install_signal_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
  // A client vanishing mid-write must not kill the daemon.
  signal(SIGPIPE, SIG_IGN);
  // A file-size limit (RLIMIT_FSIZE) must fail the write with EFBIG, which the
  // store reports, not kill the daemon.
  signal(SIGXFSZ, SIG_IGN);
}

struct Configuration {
  brainshift::server::DaemonOptions daemon;
  brainshift::PipelineParameters params;
};

// Every rank parses the same files, so a bad configuration fails on every
// rank alike and no worker is left waiting for a rank 0 that never starts.
Configuration read_configuration(const std::string& config_path, const std::string& endpoint,
                                 const std::string& events, const std::string& store, std::optional<int> igtl_port) {
  using namespace brainshift;
  Configuration c;
  if (config_path.empty()) {
    c.params = config::pipeline_parameters_from_text(config::default_config_text(), "<built-in defaults>");
    c.daemon.settings = server::server_settings_from_text(config::default_config_text(), "<built-in defaults>");
  } else {
    c.params = config::pipeline_parameters_from_file(config_path);
    c.daemon.settings = server::server_settings_from_file(config_path);
  }
  if (!endpoint.empty()) c.daemon.settings.endpoint = endpoint;
  if (!events.empty()) c.daemon.settings.events = events;
  if (!store.empty()) c.daemon.settings.store = store;
  if (igtl_port) {
    c.daemon.settings.openigtlink.enabled = true;
    c.daemon.settings.openigtlink.port = *igtl_port;
  }
  server::validate_endpoints(c.daemon.settings);
  return c;
}

// Reads the store without a running engine; safe beside a running daemon.
int export_result(const std::string& config_path, const std::string& store_override, const std::string& scan_id,
                  const std::string& out) {
  namespace fs = std::filesystem;
  try {
    if (out.empty()) throw brainshift::InputError("--export-result needs --out");
    auto settings = config_path.empty()
                        ? brainshift::server::server_settings_from_text(brainshift::config::default_config_text(), "<built-in defaults>")
                        : brainshift::server::server_settings_from_file(config_path);
    if (!store_override.empty()) settings.store = store_override;
    brainshift::server::CaseStore store(settings.store, brainshift::server::CaseStore::Mode::read_only);
    const auto record = store.find(scan_id);
    if (!record) throw brainshift::InputError("no scan " + scan_id + " in " + settings.store.string());
    if (record->state != brainshift::server::StoredScanState::done)
      throw brainshift::InputError(scan_id + " has no result (" + brainshift::server::to_string(record->state) + ")");
    for (const auto& name : store.result_file_names(scan_id)) {
      const fs::path path = fs::path(out) / name;
      fs::create_directories(path.parent_path());
      const std::string bytes = store.read_result_file(scan_id, name).value();
      std::ofstream(path, std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
      std::cout << path.string() << '\n';
    }
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "brainshiftd: " << e.what() << '\n';
    return 1;
  }
}

}  // namespace

int main(int argc, char** argv) {
  // Two malloc arenas, set before any thread exists. The engine's short-lived
  // helper threads each got an arena of their own, and with trimming off (see
  // engine_session.cpp) freed scan buffers stayed scattered over them: the
  // 200-scan soak measured ~132 MB resident; with two arenas ~115 MB, at the
  // same throughput.
  mallopt(M_ARENA_MAX, 2);
  int provided = 0;
  MPI_Init_thread(&argc, &argv, MPI_THREAD_FUNNELED, &provided);
  int rank = 0;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);

  CLI::App app{"brainshiftd: operating-room brain-shift registration daemon"};
  std::string config_path, endpoint, events, store, ready_file, log_level = "info";
  app.add_option("--config", config_path, "TOML configuration (default: the built-in config/brainshiftd.toml)")
      ->check(CLI::ExistingFile);
  app.add_option("--endpoint", endpoint, "request endpoint (ROUTER), overrides [server] endpoint");
  app.add_option("--events", events, "event endpoint (PUB), overrides [server] events");
  app.add_option("--store", store, "case store directory, overrides [server] store");
  app.add_option("--ready-file", ready_file, "write the bound endpoints here as JSON once listening");
  std::optional<int> igtl_port;
  app.add_option("--igtl-port", igtl_port,
                 "serve OpenIGTLink (3D Slicer) on this TCP port, overrides [openigtlink] port and enables it; "
                 "0: any free port (written to --ready-file as igtl_port)")
      ->check(CLI::Range(0, 65535));
  std::string export_scan, export_out;
  auto* export_opt = app.add_option("--export-result", export_scan,
                                    "write a stored scan's result files (all of them, report.png included) to --out and exit");
  app.add_option("--out", export_out, "folder for --export-result")->needs(export_opt);
  app.add_option("--log-level", log_level, "trace, debug, info, warn, error")
      ->check(CLI::IsMember({"trace", "debug", "info", "warn", "error"}));
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    MPI_Finalize();
    return code == 0 ? 0 : 2;
  }
  spdlog::set_level(spdlog::level::from_str(rank == 0 ? log_level : "warn"));
  spdlog::set_pattern(rank == 0 ? "[%Y-%m-%d %H:%M:%S.%e] [%^%l%$] %v" : "[rank " + std::to_string(rank) + "] [%l] %v");
  install_signal_handlers();

  if (!export_scan.empty()) {
    const int code = rank == 0 ? export_result(config_path, store, export_scan, export_out) : 0;
    MPI_Finalize();
    return code;
  }

  Configuration c;
  try {
    c = read_configuration(config_path, endpoint, events, store, igtl_port);
  } catch (const std::exception& e) {
    if (rank == 0) spdlog::critical("configuration: {}", e.what());
    MPI_Finalize();
    return 2;
  }
  if (provided < MPI_THREAD_FUNNELED && rank == 0)
    spdlog::warn("MPI provides thread level {} < FUNNELED; the engine stays on the main thread anyway", provided);
  c.daemon.ready_file = ready_file;

  int exit_code = 0;
  {
    brainshift::PetscSession petsc;
    if (rank != 0) {
      brainshift::run_worker_loop(MPI_COMM_WORLD);
    } else {
      std::unique_ptr<brainshift::server::EngineAdapter> engine;
      try {
        engine = std::make_unique<brainshift::server::EngineAdapter>(MPI_COMM_WORLD, c.params);
      } catch (const std::exception& e) {
        spdlog::critical("engine: {}", e.what());
        // Without a session there is no way to release the workers politely.
        int size = 1;
        MPI_Comm_size(MPI_COMM_WORLD, &size);
        if (size > 1) MPI_Abort(MPI_COMM_WORLD, 1);
        MPI_Finalize();
        return 1;
      }
      exit_code = brainshift::server::run_daemon(c.daemon, *engine, g_stop);
    }
  }
  MPI_Finalize();
  return exit_code;
}
