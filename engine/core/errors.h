#pragma once
// Error types shared by the whole engine. Callers (CLI, daemon) map them to
// exit codes and typed protocol errors, so the category matters more than the text.
#include <stdexcept>
#include <string>

namespace brainshift {

// Bad data from outside: a file, a label map, a parameter. The message names
// the offending file or field and what is wrong with it.
class InputError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A numerical stage failed (solver breakdown, folded field, no convergence).
class ComputeError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

}  // namespace brainshift
