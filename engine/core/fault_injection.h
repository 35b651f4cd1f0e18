#pragma once
// A documented fault-injection switch for the reliability tests:
//
//   BRAINSHIFT_INJECT_FAULT=<stage>@<rank>[#<n>]
//
// stage "solve": the per-scan elastic solve fails on that MPI rank, to prove
// that a failure on any rank is agreed on by all ranks and reported instead
// of hanging the job. stage "result_write" (rank 0, the daemon): a scan's
// result is announced and served from memory but never written to the store,
// as when the daemon dies between scan.done and the write; a restart must
// then compute it again from the stored scan.
// rank: the MPI rank; n: fire only the n-th time that rank reaches the stage
// (1-based; default: every time). Read once per process at start-up; unset
// (the normal case) costs nothing. A malformed value is refused at start-up
// rather than ignored.
#include <optional>
#include <string>

namespace brainshift {

struct InjectedFault {
  std::string stage;
  int rank = 0;
  int nth = 0;  // 0: every time
};

// Parses the switch's value; throws InputError when it is malformed.
InjectedFault parse_injected_fault(const std::string& text);
// The process's switch (parsed once from the environment), nullopt when unset.
const std::optional<InjectedFault>& injected_fault();

// Counts calls per process: returns true when this call of `stage` on `rank`
// is the one that must fail.
class FaultPoint {
 public:
  explicit FaultPoint(std::string stage) : stage_(std::move(stage)) {}
  bool fires(int rank);

 private:
  std::string stage_;
  int calls_ = 0;
};

}  // namespace brainshift
