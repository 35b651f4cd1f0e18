#include "fem/petsc_session.h"

#include <dlfcn.h>
#include <petscsys.h>

#include <array>
#include <climits>
#include <cstdlib>

#include "fem/petsc_check.h"

namespace brainshift {

PetscSession::PetscSession(const std::string& options) {
  PetscBool already = PETSC_FALSE;
  BS_PETSC(PetscInitialized(&already));
  if (already) return;
  // A synthetic argv: the daemon's own arguments are not PETSc options.
  static char program[] = "brainshift";
  static char no_signal[] = "-no_signal_handler";
  static std::array<char*, 3> argv_storage{program, no_signal, nullptr};
  int argc = 2;
  char** argv = argv_storage.data();
  BS_PETSC(PetscInitialize(&argc, &argv, nullptr, nullptr));
  owns_petsc_ = true;
  if (!options.empty()) BS_PETSC(PetscOptionsInsertString(nullptr, options.c_str()));
}

PetscSession::~PetscSession() {
  if (owns_petsc_) PetscFinalize();  // a destructor cannot throw; nothing to do on failure
}

bool PetscSession::active() {
  PetscBool init = PETSC_FALSE, fin = PETSC_FALSE;
  PetscInitialized(&init);
  PetscFinalized(&fin);
  return init && !fin;
}

namespace {

BlasKind classify_blas(const std::string& path) {
  // OpenBLAS exports openblas_get_config whatever its file is called.
  if (dlsym(RTLD_DEFAULT, "openblas_get_config") != nullptr) return BlasKind::openblas;
  if (path.find("openblas") != std::string::npos) return BlasKind::openblas;
  if (path.find("/blas/libblas") != std::string::npos) return BlasKind::reference;
  if (path.find("blis") != std::string::npos || path.find("atlas") != std::string::npos ||
      path.find("mkl") != std::string::npos)
    return BlasKind::other;
  return path.empty() ? BlasKind::unknown : BlasKind::other;
}

}  // namespace

BlasInfo loaded_blas() {
  BlasInfo info;
  void* dgemm = dlsym(RTLD_DEFAULT, "dgemm_");
  Dl_info where{};
  if (dgemm != nullptr && dladdr(dgemm, &where) != 0 && where.dli_fname != nullptr) {
    // Resolve the alternatives symlink (libblas.so.3 -> .../openblas-pthread/...).
    char resolved[PATH_MAX];
    info.library_path = realpath(where.dli_fname, resolved) ? resolved : where.dli_fname;
  }
  info.kind = dgemm ? classify_blas(info.library_path) : BlasKind::unknown;
  return info;
}

const char* to_string(BlasKind kind) {
  switch (kind) {
    case BlasKind::openblas: return "OpenBLAS";
    case BlasKind::reference: return "reference BLAS (slow: install libopenblas0)";
    case BlasKind::other: return "optimised BLAS (not OpenBLAS)";
    case BlasKind::unknown: break;
  }
  return "unknown";
}

}  // namespace brainshift
