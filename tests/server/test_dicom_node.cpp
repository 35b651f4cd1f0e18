// brainshift-dicom-node against DCMTK's storescu as the scanner: a complete
// series is queued once, an unknown calling AE is refused at association, an
// aborted association leaves nothing staged or queued, and a series with a
// slice missing is not queued.
#include <gtest/gtest.h>

#include <chrono>
#include <fstream>
#include <thread>

#include "core/errors.h"
#include "e2e/process.h"
#include "phantom/phantom_dicom.h"
#include "server/dicom_node.h"
#include "synthetic_head.h"
#include "temp_dir.h"

using namespace brainshift;
namespace fs = std::filesystem;

namespace {

const std::string kUidLeft = "1.2.826.0.1.3680043.2.1125.7.9";
constexpr double kQuietS = 1.0;  // the node's series_quiet_s here (the smallest it accepts)

std::vector<fs::path> dicom_files(const fs::path& dir) {
  std::vector<fs::path> out;
  if (fs::exists(dir))
    for (const auto& e : fs::directory_iterator(dir))
      if (e.path().extension() == ".dcm") out.push_back(e.path());
  return out;
}

std::vector<std::string> lines(const fs::path& file) {
  std::vector<std::string> out;
  std::ifstream in(file);
  for (std::string l; std::getline(in, l);) out.push_back(l);
  return out;
}

class DicomNode : public ::testing::Test {
 protected:
  void SetUp() override {
    port_ = e2e::free_loopback_port();
    staging_ = dir_.path() / "staging";
    // A series folder left by an earlier run: half-stored as far as anyone knows.
    fs::create_directories(staging_ / kUidLeft);
    std::ofstream(staging_ / kUidLeft / "1.dcm") << "partial";
    queue_log_ = dir_.path() / "queued.log";
    std::ofstream(dir_.path() / "node.toml")
        << "[dicom_node]\nenabled = true\nae_title = \"BRAINSHIFT\"\nport = " << port_
        << "\nallowed_peers = [\"MRSCANNER\"]\nstaging = \"staging\"\nseries_quiet_s = " << kQuietS
        << "\nqueue_command = [\"/bin/sh\", \"-c\", \"echo \\\"$1\\\" >> " << queue_log_.string()
        << "\", \"queue\"]\n";
    node_ = std::make_unique<e2e::Process>(
        std::vector<std::string>{DICOM_NODE_BIN, "--config", (dir_.path() / "node.toml").string()},
        dir_.path() / "node.out", dir_.path() / "node.err");
    // Listening once an echo from an allowed peer succeeds (bounded: 10 s).
    for (int i = 0; i < 100; ++i) {
      if (scu({ECHOSCU_BIN}, "MRSCANNER", {}).code == 0) return;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    FAIL() << "node never answered C-ECHO: " << e2e::read_file(dir_.path() / "node.err");
  }
  void TearDown() override {
    node_->signal(SIGTERM);
    EXPECT_EQ(node_->wait(10), 0) << e2e::read_file(dir_.path() / "node.err");
  }

  e2e::RunResult scu(const std::vector<std::string>& program, const std::string& calling_ae,
                     const std::vector<fs::path>& files, bool abort = false) {
    std::vector<std::string> argv = program;
    for (const std::string& a : {std::string("-aet"), calling_ae, std::string("-aec"), std::string("BRAINSHIFT")})
      argv.push_back(a);
    if (abort) argv.push_back("--abort");
    argv.push_back("127.0.0.1");
    argv.push_back(std::to_string(port_));
    for (const auto& f : files) argv.push_back(f.string());
    fs::create_directories(dir_.path() / "scu");
    return e2e::run(argv, dir_.path() / "scu", 20);
  }

  std::vector<fs::path> series(const std::string& name, const std::string& uid) {
    DicomSeriesSpec spec;
    spec.series_uid = uid;
    return write_dicom_series(test::synthetic_head().t1, dir_.path() / name, spec);
  }

  // Waits past the quiet time and the node's one-second sweep.
  static void wait_for_sweep() { std::this_thread::sleep_for(std::chrono::duration<double>(kQuietS + 1.8)); }

  test::TempDir dir_{"dicom_node"};
  int port_ = 0;
  fs::path staging_, queue_log_;
  std::unique_ptr<e2e::Process> node_;
};

const std::string kUidA = "1.2.826.0.1.3680043.2.1125.7.1";
const std::string kUidB = "1.2.826.0.1.3680043.2.1125.7.2";

TEST_F(DicomNode, CompleteSeriesIsQueuedOnceWithAllItsSlices) {
  const auto files = series("a", kUidA);
  const auto r = scu({STORESCU_BIN}, "MRSCANNER", files);
  ASSERT_EQ(r.code, 0) << r.out << r.err;
  wait_for_sweep();
  wait_for_sweep();  // a second sweep must not queue it again
  const auto queued = lines(queue_log_);
  ASSERT_EQ(queued.size(), 1u) << e2e::read_file(dir_.path() / "node.err");
  EXPECT_EQ(fs::path(queued[0]), staging_ / "queued" / kUidA);
  EXPECT_EQ(dicom_files(queued[0]).size(), files.size());
  EXPECT_FALSE(fs::exists(staging_ / kUidA));
}

TEST_F(DicomNode, UnknownCallingAeIsRefusedAndNothingIsStored) {
  const auto r = scu({STORESCU_BIN}, "INTRUDER", series("a", kUidA));
  EXPECT_NE(r.code, 0);
  EXPECT_NE((r.out + r.err).find("Rejected"), std::string::npos) << r.out << r.err;
  wait_for_sweep();
  EXPECT_TRUE(lines(queue_log_).empty());
  EXPECT_FALSE(fs::exists(staging_ / kUidA));
}

TEST_F(DicomNode, AbortedTransferRegistersNothing) {
  auto files = series("b", kUidB);
  files.resize(files.size() / 2);
  scu({STORESCU_BIN}, "MRSCANNER", files, /*abort=*/true);
  wait_for_sweep();
  EXPECT_TRUE(lines(queue_log_).empty());
  EXPECT_FALSE(fs::exists(staging_ / kUidB));
  EXPECT_FALSE(fs::exists(staging_ / "queued" / kUidB));
  EXPECT_FALSE(fs::exists(staging_ / "rejected" / kUidB));
  EXPECT_FALSE(fs::exists(staging_ / kUidLeft));  // dropped at start-up, never queued
  EXPECT_FALSE(fs::exists(staging_ / "rejected" / kUidLeft));
}

TEST_F(DicomNode, SeriesWithMissingSliceIsRejectedNotQueued) {
  auto files = series("a", kUidA);
  files.erase(files.begin() + 5);
  ASSERT_EQ(scu({STORESCU_BIN}, "MRSCANNER", files).code, 0);
  wait_for_sweep();
  EXPECT_TRUE(lines(queue_log_).empty());
  const std::string why = e2e::read_file(staging_ / "rejected" / kUidA / "reason.txt");
  EXPECT_NE(why.find("missing"), std::string::npos) << why;
}

}  // namespace

namespace {

std::string settings_error(const std::string& toml) {
  try {
    server::dicom_node_settings_from_text(toml, "test.toml", "/base");
  } catch (const InputError& e) {
    return e.what();
  }
  return "(accepted)";
}

TEST(DicomNodeSettings, ShippedConfigHasTheNodeOff) {
  const auto s = server::dicom_node_settings_from_file(BRAINSHIFT_SOURCE_DIR "/config/brainshiftd.toml");
  EXPECT_FALSE(s.enabled);
  EXPECT_EQ(s.ae_title, "BRAINSHIFT");
  EXPECT_DOUBLE_EQ(s.series_quiet_s, 30.0);
}

TEST(DicomNodeSettings, RelativeStagingIsUnderTheConfigFolder) {
  const auto s = server::dicom_node_settings_from_text(
      "[dicom_node]\nenabled = true\nallowed_peers = [\"MR\"]\nstaging = \"in\"\nqueue_command = [\"true\"]\n",
      "test.toml", "/base");
  EXPECT_EQ(s.staging, fs::path("/base/in"));
}

TEST(DicomNodeSettings, BadValuesAreRefusedByName) {
  EXPECT_NE(settings_error("[dicom_node]\nenabled = true\nstaging = \"s\"\nqueue_command = [\"true\"]\n")
                .find("allowed_peers"),
            std::string::npos);
  EXPECT_NE(settings_error("[dicom_node]\nae_title = \"SEVENTEEN_CHARS_X\"\n").find("ae_title"), std::string::npos);
  EXPECT_NE(settings_error("[dicom_node]\nseries_quiet_s = 0.1\n").find("series_quiet_s"), std::string::npos);
  EXPECT_NE(settings_error("[dicom_node]\nport = 0\n").find("port"), std::string::npos);
  EXPECT_NE(settings_error("[dicom_node]\nqueue_comand = [\"x\"]\n").find("queue_comand"), std::string::npos);
}

}  // namespace
