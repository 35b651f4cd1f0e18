// The exit-code table of client/exit_codes.h, through the real `brainshift`
// binary talking over loopback sockets to run_daemon (real request loop and
// store) with the engine double: each code for the case it names, so a code
// cannot mean two things in two commands again. (3, unreachable, is checked
// by tests/e2e/test_e2e_daemon.cpp and test_e2e_security.cpp.)
#include <gtest/gtest.h>

#include <atomic>
#include <fstream>
#include <thread>

#include "client/exit_codes.h"
#include "phantom/phantom_dicom.h"
#include "image/dicom_series.h"
#include "image/nrrd_io.h"
#include "synthetic_head.h"
#include "image/nifti_io.h"
#include "protocol/requests.h"
#include "protocol/transport.h"
#include "server/daemon.h"
#include "tests/e2e/process.h"
#include "test_support.h"

using namespace brainshift;
using namespace brainshift::server;
using namespace std::chrono_literals;
namespace fs = std::filesystem;
namespace cli = brainshift::cli;

namespace {

class LoopbackDaemon {
 public:
  LoopbackDaemon() {
    DaemonOptions o;
    o.settings.endpoint = "tcp://127.0.0.1:*";
    o.settings.events = "tcp://127.0.0.1:*";
    o.settings.store = dir.path() / "store";
    o.settings.preop.kind = DefaultPreop::Kind::none;
    o.ready_file = dir.path() / "ready.json";
    daemon_ = std::make_unique<test::DaemonThread>(o, engine);
  }
  e2e::RunResult client(std::vector<std::string> args) {
    std::vector<std::string> argv{BRAINSHIFT_BIN, "--server", daemon_->endpoint(), "--events", daemon_->events(),
                                  "--timeout", "10"};
    argv.insert(argv.end(), args.begin(), args.end());
    return e2e::run(argv, dir.path(), 60);
  }
  fs::path write(const std::string& name, const std::string& bytes) {
    const fs::path p = dir.path() / name;
    std::ofstream(p, std::ios::binary) << bytes;
    return p;
  }

  test::TempDir dir;
  test::FakeEngine engine;

 private:
  std::unique_ptr<test::DaemonThread> daemon_;
};

TEST(ClientExitCodes, EachCodeForTheCaseItNames) {
  LoopbackDaemon d;
  const LabelImage labels = test::ball_labels(10);
  const fs::path labels_file = d.write("labels.nii.gz", label_image_to_bytes(labels, true)).string();
  const fs::path t1_file = d.write("t1.nii.gz", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true));

  // 1: the server answered with an error (no preop yet: not_ready).
  e2e::RunResult r = d.client({"push", "--labels", labels_file.string()});
  EXPECT_EQ(r.code, cli::kExitError) << r.err;
  // 2: usage; and a local file the command cannot read.
  EXPECT_EQ(d.client({"push"}).code, cli::kExitUsage);
  EXPECT_EQ(d.client({"push", "--labels", (d.dir.path() / "missing.nii.gz").string()}).code, cli::kExitUsage);

  r = d.client({"load-preop", "--image", t1_file.string(), "--labels", labels_file.string(), "--wait"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;

  // 0: a non-rigid result.
  r = d.client({"push", "--labels", labels_file.string(), "--id", "scan-ok", "--wait", "--wait-timeout", "30"});
  EXPECT_EQ(r.code, cli::kExitOk) << r.err;

  // 4: the affine-only fallback, as register says it, known at scan.done:
  // the deferred metrics.json is held back until the command has exited.
  // The hook is set once scan-ok's deferred outputs are made: set earlier, it
  // held scan-ok's instead and the worker with them (a loaded machine's race).
  for (int i = 0; i < 600 && *d.engine.deferred_renders < 1; ++i) std::this_thread::sleep_for(50ms);
  ASSERT_GE(d.engine.deferred_renders->load(), 1) << "scan-ok's deferred outputs were never made";
  d.engine.fallback_next_scan = true;
  std::atomic<bool> client_exited{false}, metrics_held{false};
  d.engine.while_rendering_deferred = [&] {
    metrics_held = true;
    for (int i = 0; i < 800 && !client_exited; ++i) std::this_thread::sleep_for(50ms);
  };
  r = d.client({"push", "--labels", labels_file.string(), "--id", "scan-fallback", "--wait", "--wait-timeout", "30"});
  client_exited = true;
  EXPECT_EQ(r.code, cli::kExitFallback) << r.err;
  EXPECT_NE(r.err.find("AFFINE-ONLY"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("fake: surface match diverged"), std::string::npos) << r.err;
  // Had the command waited for metrics.json, it would have timed out (3).
  for (int i = 0; i < 200 && !metrics_held; ++i) std::this_thread::sleep_for(50ms);
  EXPECT_TRUE(metrics_held.load()) << "the fallback's metrics.json was not deferred";

  // 5: the daemon's registration failed; pulling that scan says the same.
  d.engine.fail_next_scan = true;
  r = d.client({"push", "--labels", labels_file.string(), "--id", "scan-failed", "--wait", "--wait-timeout", "30"});
  EXPECT_EQ(r.code, cli::kExitScanFailed) << r.err;
  const std::string failed_id = r.out.substr(0, r.out.find('\n'));
  r = d.client({"pull", "--scan", failed_id, "--out", (d.dir.path() / "pulled").string(), "--parts", "metrics"});
  EXPECT_EQ(r.code, cli::kExitScanFailed) << r.err;
}

// A small series of the synthetic head, and a box of brain round a box of
// ventricle on its grid (the labels pushed with it).
DicomSeriesSpec small_series() {
  DicomSeriesSpec spec;
  spec.columns = 20;
  spec.rows = 18;
  spec.slices = 12;
  return spec;
}
LabelImage box_labels_on(const DicomSeriesSpec& spec) {
  LabelImage labels(dicom_series_grid_ras(spec));
  for (int k = 2; k < 10; ++k)
    for (int j = 3; j < 15; ++j)
      for (int i = 3; i < 17; ++i) labels.at(i, j, k) = (i > 8 && i < 12 && j > 7 && j < 11) ? 2 : 1;
  return labels;
}

// `push --dicom`: the series is read in the client (brainshift hands the
// command to brainshift-offline) and arrives as the NIfTI image of the scan.
TEST(ClientExitCodes, PushDicomSendsTheSeriesAsTheScansImage) {
  LoopbackDaemon d;
  DicomSeriesSpec spec = small_series();
  spec.rescale_slope = 0.5;
  write_dicom_series(test::synthetic_head().t1, d.dir.path() / "series", spec);
  const LabelImage labels = box_labels_on(spec);
  const fs::path labels_file = d.write("dicom_labels.nii.gz", label_image_to_bytes(labels, true));
  ASSERT_EQ(d.client({"load-preop", "--image",
                      d.write("t1.nii.gz", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true))
                          .string(),
                      "--labels", labels_file.string(), "--wait"})
                .code,
            cli::kExitOk);

  e2e::RunResult r = d.client({"push", "--labels", labels_file.string(), "--dicom", (d.dir.path() / "series").string(),
                               "--wait", "--wait-timeout", "30"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;
  ASSERT_TRUE(d.engine.last_scan_image.has_value());
  const ImageF expected = read_dicom_series(d.dir.path() / "series", "", std::size_t{1} << 30);
  EXPECT_TRUE(d.engine.last_scan_image->grid.same_geometry(expected.grid));
  EXPECT_EQ(d.engine.last_scan_image->voxels, expected.voxels);

  // The series alone (PROTOCOL.md 5.3, revision 4): sent without labels, the
  // daemon segments it; pull --scene brings the segmentation into the scene.
  r = d.client({"push", "--dicom", (d.dir.path() / "series").string(), "--wait", "--wait-timeout", "30"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;
  EXPECT_FALSE(d.engine.last_scan_had_labels);
  EXPECT_EQ(d.engine.last_scan_image->voxels, expected.voxels);
  const std::string image_only = r.out.substr(0, r.out.find('\n'));
  r = d.client({"pull", "--scan", image_only, "--out", (d.dir.path() / "image_only").string(), "--scene"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;
  EXPECT_TRUE(fs::is_regular_file(d.dir.path() / "image_only" / "intraop_labels.nii.gz")) << r.out;
  EXPECT_NE(e2e::read_file(d.dir.path() / "image_only" / "scene.mrml").find("intraop_labels.nii.gz"),
            std::string::npos);

  // The T1 as NRRD (as Slicer saves it): converted to NIfTI by the client too.
  write_nrrd_scalar(d.dir.path() / "t1.nrrd", expected);
  r = d.client({"push", "--labels", labels_file.string(), "--image", (d.dir.path() / "t1.nrrd").string(), "--wait",
                "--wait-timeout", "30"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;
  EXPECT_TRUE(d.engine.last_scan_image->grid.same_geometry(expected.grid));
  EXPECT_EQ(d.engine.last_scan_image->voxels, expected.voxels);
  const std::string scan = r.out.substr(0, r.out.find('\n'));

  // pull --format nrrd: NRRD copies of the images and field, and the Slicer scene uses them.
  const fs::path out = d.dir.path() / "pulled";
  r = d.client({"pull", "--scan", scan, "--out", out.string(), "--format", "nrrd", "--scene"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;
  for (const char* f : {"field.nrrd", "warped_image.nrrd", "warped_labels.nrrd"})
    EXPECT_TRUE(fs::is_regular_file(out / f)) << f << "\n" << r.out;
  EXPECT_EQ(read_nrrd_labels(out / "warped_labels.nrrd", std::size_t{1} << 30).voxels,
            read_label_image(out / "warped_labels.nii.gz").voxels);
  const std::string scene = e2e::read_file(out / "scene.mrml");
  EXPECT_NE(scene.find("field.nrrd"), std::string::npos) << scene;
  EXPECT_NE(scene.find("warped_labels.nrrd"), std::string::npos);
  EXPECT_NE(e2e::read_file(out / "field.nrrd").find("displacement field type:=resampling"), std::string::npos);

  // Refusals are usage errors naming the folder's problem.
  r = d.client({"push", "--labels", labels_file.string(), "--dicom", (d.dir.path() / "nowhere").string()});
  EXPECT_EQ(r.code, cli::kExitUsage);
  EXPECT_NE(r.err.find("not a folder"), std::string::npos) << r.err;
  r = d.client({"push", "--labels", labels_file.string(), "--dicom", (d.dir.path() / "series").string(), "--image",
                labels_file.string()});
  EXPECT_EQ(r.code, cli::kExitUsage);
  EXPECT_NE(r.err.find("not both"), std::string::npos) << r.err;
}

// Patient identity (PROTOCOL.md 5.3): a preop loaded for a patient refuses a
// DICOM series of another patient (push sends the series' PatientID), and
// nothing of it is registered or kept; --patient-id that contradicts the
// series is a usage error; the patient's own series is taken.
TEST(ClientExitCodes, PushDicomOfAnotherPatientIsRefused) {
  LoopbackDaemon d;
  DicomSeriesSpec spec = small_series();
  write_dicom_series(test::synthetic_head().t1, d.dir.path() / "other", spec);  // PatientID PHANTOM01
  spec.patient_id = "MRN-0042";
  write_dicom_series(test::synthetic_head().t1, d.dir.path() / "own", spec);
  const LabelImage labels = box_labels_on(spec);
  const fs::path labels_file = d.write("dicom_labels.nii.gz", label_image_to_bytes(labels, true));
  const fs::path t1_file =
      d.write("t1.nii.gz", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true));
  e2e::RunResult r = d.client({"load-preop", "--image", t1_file.string(), "--labels", labels_file.string(),
                               "--patient-id", "MRN-0042", "--wait"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;
  r = d.client({"status"});
  EXPECT_NE(r.out.find("(patient MRN-0042)"), std::string::npos) << r.out;

  r = d.client({"push", "--dicom", (d.dir.path() / "other").string(), "--id", "wrong-patient", "--wait"});
  EXPECT_EQ(r.code, cli::kExitError) << r.err;
  EXPECT_NE(r.err.find("of patient \"PHANTOM01\""), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("NOT stored"), std::string::npos) << r.err;
  EXPECT_FALSE(d.engine.last_scan_image.has_value()) << "nothing of the other patient's scan may reach the engine";
  r = d.client({"list"});
  EXPECT_EQ(r.out.find("wrong-patient"), std::string::npos) << r.out;

  r = d.client({"push", "--dicom", (d.dir.path() / "other").string(), "--patient-id", "MRN-0042"});
  EXPECT_EQ(r.code, cli::kExitUsage) << r.err;
  EXPECT_NE(r.err.find("the DICOM series is of patient \"PHANTOM01\""), std::string::npos) << r.err;

  // A PatientID in a character set the files do not declare is no text to
  // compare: the push says so instead of sending it unchecked.
  spec.patient_id = "M\xDCLLER-7";
  write_dicom_series(test::synthetic_head().t1, d.dir.path() / "undeclared", spec);
  r = d.client({"push", "--dicom", (d.dir.path() / "undeclared").string()});
  EXPECT_EQ(r.code, cli::kExitUsage) << r.err;
  EXPECT_NE(r.err.find("give the patient with --patient-id"), std::string::npos) << r.err;

  r = d.client({"push", "--dicom", (d.dir.path() / "own").string(), "--wait", "--wait-timeout", "30"});
  ASSERT_EQ(r.code, cli::kExitOk) << r.err;
  EXPECT_TRUE(d.engine.last_scan_image.has_value());

  // register, with both images as DICOM series, compares their patients the
  // same way, before any of the preop's warm-up is spent.
  const fs::path t0 = d.dir.path() / "register_other_patient";
  r = d.client({"register", "--preop-dicom", (d.dir.path() / "own").string(), "--preop-labels", labels_file.string(),
                "--intraop-dicom", (d.dir.path() / "other").string(), "--out", t0.string()});
  EXPECT_EQ(r.code, cli::kExitError) << r.err;
  EXPECT_NE(r.err.find("the intraop series is of patient \"PHANTOM01\" and the preop series of patient \"MRN-0042\""),
            std::string::npos)
      << r.err;
  EXPECT_FALSE(fs::exists(t0));
}

// A server of an earlier revision (PROTOCOL.md 10) does not know labels.get
// and answers unknown_type: `pull --scene` says so and stops before it pulls
// anything (the client has no label table of its own).
TEST(ClientExitCodes, PullSceneFromAServerWithoutLabelsGetStopsFirst) {
  zmq::context_t context;
  zmq::socket_t router(context, zmq::socket_type::router);
  router.bind("tcp://127.0.0.1:*");
  const std::string endpoint = router.get(zmq::sockopt::last_endpoint);
  std::atomic<bool> stop{false};
  std::vector<std::string> types;
  std::thread server([&] {
    for (int i = 0; i < 600 && !stop; ++i) {  // at most 60 s
      const auto r = protocol::transport::receive_request(router, 100ms);
      if (!r || r->wire.empty()) continue;
      const auto header = nlohmann::json::parse(r->wire.front());
      types.push_back(header.value("type", ""));
      protocol::transport::send_reply(router, r->envelope,
                           protocol::make_error_reply(header.value("request_id", ""), protocol::ErrorCode::kUnknownType,
                                                      "\"" + types.back() + "\" is not a message type"));
    }
  });
  test::TempDir dir("old-server");
  const e2e::RunResult r = e2e::run({BRAINSHIFT_BIN, "--server", endpoint, "--timeout", "10", "pull", "--scan", "s-1",
                                     "--out", (dir.path() / "pulled").string(), "--scene"},
                                    dir.path(), 60);
  stop = true;
  server.join();
  EXPECT_EQ(r.code, cli::kExitError) << r.err;
  EXPECT_NE(r.err.find("does not serve its label table"), std::string::npos) << r.err;
  EXPECT_EQ(types, std::vector<std::string>{"labels.get"});  // nothing was asked for after it
  EXPECT_FALSE(fs::exists(dir.path() / "pulled" / "scene.mrml"));
}

}  // namespace
