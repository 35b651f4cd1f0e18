#include "offline_forwarding.h"

#include <unistd.h>

#include <cctype>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include "connection.h"

namespace brainshift::cli {
namespace fs = std::filesystem;

namespace {

fs::path offline_executable() {
  std::error_code ec;
  const fs::path self = fs::read_symlink("/proc/self/exe", ec);
  return (ec ? fs::path(".") : self.parent_path()) / kOfflineExecutable;
}

}  // namespace

int exec_offline(int argc, char** argv) {
  const fs::path target = offline_executable();
  const std::string program = target.string();
  // argv[0] stays "brainshift": usage and messages name the command the user typed.
  std::vector<char*> args(argv, argv + argc);
  args.push_back(nullptr);
  ::execv(program.c_str(), args.data());
  std::cerr << "brainshift: cannot run " << program << " (the offline commands live there): "
            << std::strerror(errno) << '\n';
  return kExitUsage;
}

bool is_nrrd_pull(int argc, char** argv) {
  bool pull = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "pull") pull = true;
    else if (pull && (a == "--format" || a.rfind("--format=", 0) == 0)) return true;
  }
  return false;
}

bool is_nrrd_name(const std::string& path) {
  auto ends = [&](const char* e) {
    const std::size_t n = std::strlen(e);
    if (path.size() < n) return false;
    for (std::size_t i = 0; i < n; ++i)
      if (std::tolower(static_cast<unsigned char>(path[path.size() - n + i])) != e[i]) return false;
    return true;
  };
  return ends(".nrrd") || ends(".nhdr");
}

bool is_converting_push(int argc, char** argv) {
  bool push = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "push") push = true;
    else if (push && (a == "--dicom" || a.rfind("--dicom=", 0) == 0 || is_nrrd_name(a))) return true;
  }
  return false;
}

void add_offline_forwarding(CLI::App& app, int argc, char** argv, int* exit_code) {
  for (const auto& [name, what] : {std::pair{"register", "one-shot registration in this process (no daemon)"},
                                   std::pair{"phantom", "make a synthetic brain-shift case with a known field"}}) {
    CLI::App* sub = app.add_subcommand(name, std::string(what) + " (runs " + kOfflineExecutable + ")");
    // Every argument after the subcommand, --help included, is its own:
    // brainshift-offline parses them.
    sub->prefix_command();
    sub->set_help_flag();
    sub->callback([argc, argv, exit_code] { *exit_code = exec_offline(argc, argv); });
  }
}

}  // namespace brainshift::cli
