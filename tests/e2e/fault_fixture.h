#pragma once
// Shared by the fault tests (test_e2e_faults_crash, _io, _mpi): the synthetic
// inputs made once per executable in a work folder kept when a test failed,
// the daemon's spec on them, and readings of events, scan lists and the store.
#include <chrono>
#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "daemon_harness.h"
#include "temp_dir.h"  // tests/support

namespace brainshift::e2e {

namespace fs = std::filesystem;
using nlohmann::json;

struct Inputs {
  test::TempDir tmp{"faults"};
  std::filesystem::path dir = tmp.path();
  std::filesystem::path config;
  std::string preop_t1, preop_labels;
  std::vector<ScanBytes> scans;
};

// Made once for all tests of the executable (the synthetic images take a moment).
Inputs& inputs();

DaemonSpec spec(const std::filesystem::path& store, const std::string& name, int mpi_ranks = 0);

bool is_scan_event(const protocol::Message& m, protocol::MessageType type, const std::string& scan_id);
bool progress_at(const protocol::Message& m, const std::string& stage, double min_fraction);
std::string scan_id_of(const protocol::Message& push_reply);

// Pushes a scan and, while the daemon answers `busy` (its queue is full: the
// documented answer is "retry later"), waits and pushes again, as a scanner-side
// client must. A busy push was neither stored nor acknowledged, so pushing it
// again cannot make a second scan. Returns the last reply (a scan.push reply or
// another error); *busy_replies counts the retries.
protocol::Message push_retrying_busy(Client& c, const ScanBytes& scan, const std::string& client_id,
                                     std::chrono::seconds timeout, int* busy_replies = nullptr);

// Polls scan.list until no scan is queued or processing.
protocol::ScanListReply wait_all_finished(Client& c, std::chrono::seconds timeout);

// Files of unfinished writes under store (.tmp-* and *.tmp).
std::vector<std::filesystem::path> temporary_leftovers(const std::filesystem::path& store);

}  // namespace brainshift::e2e
