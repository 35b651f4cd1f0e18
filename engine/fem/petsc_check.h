#pragma once
// Internal to engine/fem: turn PETSc error codes into C++ exceptions, so that
// no PETSc failure is silently ignored and callers see one error category.
#include <petscsys.h>

#include <string>

#include "core/errors.h"

namespace brainshift::fem_detail {

[[noreturn]] inline void throw_petsc_error(PetscErrorCode code, const char* call,
                                           const char* file, int line) {
  const char* text = nullptr;
  PetscErrorMessage(code, &text, nullptr);
  throw ComputeError(std::string("PETSc error ") + std::to_string(static_cast<int>(code)) +
                     " (" + (text ? text : "unknown") + ") in " + call + " at " + file + ":" +
                     std::to_string(line));
}

}  // namespace brainshift::fem_detail

// PetscCall-style check that throws ComputeError instead of returning a code.
#define BS_PETSC(call)                                                              \
  do {                                                                              \
    const PetscErrorCode bs_petsc_ierr_ = (call);                                   \
    if (bs_petsc_ierr_ != 0)                                                        \
      ::brainshift::fem_detail::throw_petsc_error(bs_petsc_ierr_, #call, __FILE__, \
                                                  __LINE__);                        \
  } while (0)
