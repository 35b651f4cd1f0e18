#pragma once
// What every engine benchmark does first: ranks > 0 serve rank 0's
// collective steps until it is done; rank 0 takes the configuration.
#include <mpi.h>

#include <cstdio>
#include <exception>
#include <string>

#include "config_file.h"
#include "pipeline/engine_session.h"

namespace brainshift::bench {

// false on ranks > 0, after their worker loop has ended: return from main.
inline bool drive_from_this_rank() {
  int rank = 0;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  if (rank == 0) return true;
  run_worker_loop(MPI_COMM_WORLD);
  return false;
}

// The default configuration, or the file given. A configuration that cannot
// be read ends the run with its reason (and the other ranks with it), not
// with an uncaught exception.
inline PipelineParameters parameters(const std::string& config_path) {
  try {
    return config_path.empty() ? config::pipeline_parameters_from_text(config::default_config_text(), "built-in")
                               : config::pipeline_parameters_from_file(config_path);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: configuration %s: %s\n", config_path.empty() ? "(built-in)" : config_path.c_str(),
                 e.what());
    MPI_Abort(MPI_COMM_WORLD, 2);
    throw;  // not reached
  }
}

}  // namespace brainshift::bench
