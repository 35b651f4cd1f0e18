#include "command_support.h"

#include <algorithm>
#include <atomic>
#include <csignal>
#include <fstream>

#include "connection.h"
#include "core/errors.h"
#include "core/file_bytes.h"

namespace brainshift::cli {
namespace fs = std::filesystem;

namespace {
std::atomic<bool> g_interrupted{false};
extern "C" void on_interrupt(int) { g_interrupted = true; }
}  // namespace

std::chrono::milliseconds as_ms(double seconds) {
  return std::chrono::milliseconds(static_cast<long long>(std::max(0.05, seconds) * 1000.0));
}

std::string read_file(const std::string& path) {
  try {
    return read_whole_file(path);
  } catch (const InputError& e) {
    throw CommandError(kExitUsage, e.what());
  }
}

void write_file(const fs::path& path, const std::string& bytes) {
  fs::create_directories(path.parent_path());
  const fs::path tmp = path.string() + ".partial";
  {
    std::ofstream out(tmp, std::ios::binary);
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    if (!out) throw CommandError(kExitUsage, tmp.string() + ": cannot write");
  }
  fs::rename(tmp, path);
}

void stop_on_interrupt() {
  std::signal(SIGINT, on_interrupt);
  std::signal(SIGTERM, on_interrupt);
}

bool interrupted() { return g_interrupted; }

}  // namespace brainshift::cli
