// The scanner's DICOM node end to end: storescu sends a series to
// brainshift-dicom-node, which queues it on the real daemon with
// `brainshift push --dicom` (its queue_command) once the series is quiet.
#include <gtest/gtest.h>

#include <chrono>
#include <fstream>
#include <thread>

#include "daemon_harness.h"
#include "synthetic_case.h"
#include "image/nifti_io.h"
#include "phantom/phantom_dicom.h"
#include "temp_dir.h"

using namespace brainshift;
using namespace brainshift::e2e;
using namespace std::chrono_literals;
namespace fs = std::filesystem;

namespace {

TEST(DicomNodeE2E, SeriesFromStorescuIsQueuedOnTheDaemonOnce) {
  test::TempDir tmp("e2e_dicom_node");
  const fs::path dir = tmp.path();
  write_synthetic_preop(dir);
  write_synthetic_scan(dir, "intraop", Eigen::Vector3d(0, 0, 2));
  // The intraop T1 as the scanner sends it; the labels stay on its grid.
  const ImageF t1 = read_scalar_image(dir / "intraop_t1.nii.gz", std::size_t{1} << 30);
  DicomSeriesSpec spec = dicom_series_spec_of(t1);
  spec.patient_id = "MRN-0042";
  spec.series_uid = "1.2.826.0.1.3680043.2.1125.42.1";
  const auto files = write_dicom_series(t1, dir / "series", spec);
  // The same images from another patient's exam (PatientID PHANTOM01).
  spec.patient_id = "PHANTOM01";
  spec.series_uid = "1.2.826.0.1.3680043.2.1125.43.1";
  const auto other_files = write_dicom_series(t1, dir / "other_patient", spec);

  std::ofstream(dir / "test.toml") << test_config_text(4);
  Daemon d(DaemonSpec{dir, dir / "test.toml", dir / "store", "dicom", 0, {}, {}});
  Client c(d.endpoint);
  c.load_preop(read_file(dir / "preop_t1.nii.gz"), read_file(dir / "preop_labels.nii.gz"), "MRN-0042");
  ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();

  const int port = free_loopback_port();
  std::ofstream(dir / "node.toml") << "[dicom_node]\nenabled = true\nport = " << port
                                   << "\nallowed_peers = [\"MR_OR1\"]\nstaging = \"staging\"\nseries_quiet_s = 1\n"
                                   << "queue_command = [\"" << BRAINSHIFT_BIN << "\", \"--server\", \"" << d.endpoint
                                   << "\", \"push\", \"--labels\", \"" << (dir / "intraop_labels.nii.gz").string()
                                   << "\", \"--id\", \"or1-dicom\", \"--dicom\"]\n";
  Process node({DICOM_NODE_BIN, "--config", (dir / "node.toml").string()}, dir / "node.out", dir / "node.err");
  std::vector<std::string> scu = {STORESCU_BIN, "-aet", "MR_OR1", "-aec", "BRAINSHIFT", "127.0.0.1",
                                  std::to_string(port)};
  for (const auto& f : files) scu.push_back(f.string());
  RunResult sent;
  for (int i = 0; i < 50; ++i) {  // until the node listens (bounded: 10 s)
    sent = run(scu, dir, 60);
    if (sent.code == 0) break;
    std::this_thread::sleep_for(200ms);
  }
  ASSERT_EQ(sent.code, 0) << sent.out << sent.err << read_file(dir / "node.err");

  std::vector<protocol::ScanSummary> scans;
  for (int i = 0; i < 60 && scans.empty(); ++i) {  // quiet time, sweep and push: bounded at 30 s
    std::this_thread::sleep_for(500ms);
    scans = c.list().scans;
  }
  std::this_thread::sleep_for(3s);  // two more sweeps: queued once, not again
  scans = c.list().scans;
  ASSERT_EQ(scans.size(), 1u) << read_file(dir / "node.err") << d.log();
  EXPECT_EQ(scans[0].client_scan_id, std::optional<std::string>("or1-dicom"));

  // Another patient's series: the daemon refuses the node's push, nothing is
  // stored, and the node keeps the series in rejected/ with the daemon's
  // reason (PROTOCOL.md 5.3, "Patient identity").
  std::vector<std::string> scu_other = {STORESCU_BIN, "-aet", "MR_OR1", "-aec", "BRAINSHIFT", "127.0.0.1",
                                        std::to_string(port)};
  for (const auto& f : other_files) scu_other.push_back(f.string());
  ASSERT_EQ(run(scu_other, dir, 60).code, 0);
  const fs::path reason = dir / "staging" / "rejected" / spec.series_uid / "reason.txt";
  for (int i = 0; i < 60 && !fs::exists(reason); ++i) std::this_thread::sleep_for(500ms);
  ASSERT_TRUE(fs::exists(reason)) << read_file(dir / "node.err");
  const std::string why = read_file(reason);
  EXPECT_NE(why.find("the scan is of patient \"PHANTOM01\""), std::string::npos) << why;
  EXPECT_EQ(c.list().scans.size(), 1u);
  node.signal(SIGTERM);
  EXPECT_EQ(node.wait(10), 0) << read_file(dir / "node.err");
}

}  // namespace
