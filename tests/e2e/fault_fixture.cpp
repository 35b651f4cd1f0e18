#include "fault_fixture.h"

#include <gtest/gtest.h>

#include <fstream>
#include <memory>
#include <thread>

namespace brainshift::e2e {

using namespace protocol;
using namespace std::chrono_literals;

namespace {

std::unique_ptr<Inputs> g_inputs;

// Removes the work folder unless a test failed (then it is kept for a post-mortem).
class CleanUp : public ::testing::Environment {
 public:
  void TearDown() override {
    if (g_inputs && ::testing::UnitTest::GetInstance()->failed_test_count() > 0) g_inputs->tmp.keep();
    g_inputs.reset();
  }
};
const auto* const g_cleanup = ::testing::AddGlobalTestEnvironment(new CleanUp);

}  // namespace

Inputs& inputs() {
  if (!g_inputs) {
    g_inputs = std::make_unique<Inputs>();
    Inputs* i = g_inputs.get();
    i->config = i->dir / "test.toml";
    std::ofstream(i->config) << test_config_text(8);
    i->scans = write_synthetic_inputs(i->dir, 3);
    i->preop_t1 = read_file(i->dir / "preop_t1.nii.gz");
    i->preop_labels = read_file(i->dir / "preop_labels.nii.gz");
  }
  return *g_inputs;
}

DaemonSpec spec(const fs::path& store, const std::string& name, int mpi_ranks) {
  return DaemonSpec{inputs().dir, inputs().config, store, name, mpi_ranks, {}, {}};
}

bool is_scan_event(const Message& m, MessageType type, const std::string& scan_id) {
  if (m.type() != type) return false;
  if (type == MessageType::kEventScanDone) return parse_scan_done_event(m).scan_id == scan_id;
  if (type == MessageType::kEventScanFailed) return parse_scan_failed_event(m).scan_id == scan_id;
  return false;
}

bool progress_at(const Message& m, const std::string& stage, double min_fraction) {
  if (m.type() != MessageType::kEventScanProgress) return false;
  const auto p = parse_scan_progress_event(m);
  return p.stage == stage && p.fraction >= min_fraction;
}

std::string scan_id_of(const Message& push_reply) {
  throw_if_error(push_reply);
  return parse_scan_push_reply(push_reply).scan_id;
}

Message push_retrying_busy(Client& c, const ScanBytes& scan, const std::string& client_id,
                           std::chrono::seconds timeout, int* busy_replies) {
  const auto until = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    Message reply = c.push(scan.labels, scan.image, client_id);
    const bool busy = reply.type() == MessageType::kError && parse_error_reply(reply).code == ErrorCode::kBusy;
    if (!busy || std::chrono::steady_clock::now() > until) return reply;
    if (busy_replies) ++*busy_replies;
    std::this_thread::sleep_for(250ms);
  }
}

ScanListReply wait_all_finished(Client& c, std::chrono::seconds timeout) {
  const auto until = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    ScanListReply list = c.list();
    bool busy = false;
    for (const auto& s : list.scans) busy |= s.state == ScanState::kQueued || s.state == ScanState::kProcessing;
    if (!busy || std::chrono::steady_clock::now() > until) return list;
    std::this_thread::sleep_for(200ms);
  }
}

std::vector<fs::path> temporary_leftovers(const fs::path& store) {
  std::vector<fs::path> out;
  for (const auto& e : fs::recursive_directory_iterator(store)) {
    const std::string n = e.path().filename().string();
    if (n.rfind(".tmp-", 0) == 0 || (n.size() > 4 && n.substr(n.size() - 4) == ".tmp")) out.push_back(e.path());
  }
  return out;
}

}  // namespace brainshift::e2e
