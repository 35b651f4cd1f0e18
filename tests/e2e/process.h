#pragma once
// Child processes for the end-to-end tests (posix_spawn, output to files).
#include <sys/types.h>

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace brainshift::e2e {

class Process {
 public:
  // stdout/stderr go to the given files.
  Process(const std::vector<std::string>& argv, const std::filesystem::path& out, const std::filesystem::path& err);
  ~Process();  // kills (SIGKILL) a child still running
  Process(const Process&) = delete;
  Process& operator=(const Process&) = delete;

  void signal(int sig) const;
  // Exit code (128+signal when killed by one); nullopt on timeout.
  std::optional<int> wait(double timeout_s);
  bool running();
  pid_t pid() const { return pid_; }

 private:
  pid_t pid_ = -1;
  std::optional<int> status_;
};

struct RunResult {
  int code = -1;  // -1: timed out (and killed)
  std::string out, err;
  double seconds = 0;
};

// Runs to completion (or kills after timeout_s); work_dir holds the output files.
RunResult run(const std::vector<std::string>& argv, const std::filesystem::path& work_dir, double timeout_s);

std::string read_file(const std::filesystem::path& path);

// A loopback TCP port that was free a moment ago (for a server under test
// that needs its port on the command line, e.g. a DICOM node).
int free_loopback_port();

}  // namespace brainshift::e2e
