#pragma once
// Process-wide PETSc lifetime and a check of which BLAS the process loaded.
#include <string>

namespace brainshift {

// RAII PetscInitialize / PetscFinalize. Construct one per process before any
// ElasticModel, destroy it after the last one.
// - PETSc is started with -no_signal_handler: the daemon owns SIGTERM/SIGINT
//   and must shut down cleanly itself instead of PETSc aborting the process.
// - Safe when MPI is already initialised (PETSc then leaves MPI_Finalize to
//   whoever called MPI_Init) and when PETSc is already initialised (this
//   session then neither initialises nor finalises).
// - PETSc reads no command line here (the daemon parses its own); extra
//   global options can be passed in `options` ("-log_view" etc.), and the
//   PETSC_OPTIONS environment variable is honoured as usual.
class PetscSession {
 public:
  explicit PetscSession(const std::string& options = "");
  ~PetscSession();
  PetscSession(const PetscSession&) = delete;
  PetscSession& operator=(const PetscSession&) = delete;

  // True between a successful PetscInitialize and PetscFinalize.
  static bool active();

 private:
  bool owns_petsc_ = false;
};

enum class BlasKind { openblas, reference, other, unknown };

struct BlasInfo {
  BlasKind kind = BlasKind::unknown;
  std::string library_path;  // resolved file that provides dgemm_, "" if unknown
};

// Which shared library provides dgemm_ in this process. Debian's PETSc links
// libblas.so.3, which the alternatives system may point at the reference BLAS:
// MUMPS took 82 s with it vs 8.4 s with OpenBLAS (docs/DESIGN.md, "Measured
// facts"), so start-up should warn when kind == reference.
BlasInfo loaded_blas();
const char* to_string(BlasKind kind);

}  // namespace brainshift
