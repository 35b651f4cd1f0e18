#pragma once
// What every network command of `brainshift` shares: its timeouts, its local
// files (read as usage errors, written atomically) and Ctrl-C.
#include <chrono>
#include <filesystem>
#include <string>

namespace brainshift::cli {

// Seconds as a timeout, at least 50 ms.
std::chrono::milliseconds as_ms(double seconds);

// The file's bytes; CommandError(kExitUsage) when it cannot be read.
std::string read_file(const std::string& path);

// Written to PATH.partial and renamed: a reader never sees half a field.
// CommandError(kExitUsage) when it cannot be written.
void write_file(const std::filesystem::path& path, const std::string& bytes);

// From now on SIGINT and SIGTERM end the waiting loops (interrupted()) instead
// of the process.
void stop_on_interrupt();
bool interrupted();

}  // namespace brainshift::cli
