// A scan pushed as an image alone, end to end through the real binaries
// (PROTOCOL.md 5.3, revision 4): `brainshift push --image I --wait` with no
// labels, the daemon segments the image, `pull` serves the segmentation it
// used (intraop_labels, segmentation_confidence) on the intraop grid in the
// label table's values; the corrected-labels push with the same image is the
// ordinary path; bad images are refused with the reason while the daemon keeps
// serving; and a scan stored as an image alone is computed again from the
// store after a crash.
#include <gtest/gtest.h>

#include <algorithm>
#include <csignal>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "config_file.h"
#include "daemon_harness.h"
#include "igtl_receiver.h"
#include "image/nifti_io.h"
#include "image/resample.h"
#include "process.h"
#include "protocol/result_outputs.h"
#include "protocol/timing_log.h"
#include "synthetic_case.h"
#include "synthetic_head.h"
#include "temp_dir.h"

using namespace brainshift;
using namespace brainshift::e2e;
using namespace std::chrono_literals;
namespace fs = std::filesystem;

namespace {

const Eigen::Vector3d kShiftMm(3.0, -2.0, 2.0);

// The harness's coarse mesh, and `brainshift shutdown` allowed.
std::string config_text() { return test_config_text(4) + "\n[security]\nallow_unauthenticated_shutdown = true\n"; }

class ImageOnlyE2E : public ::testing::Test {
 protected:
  test::TempDir tmp{"e2e-image-only"};
  fs::path dir = tmp.path();

  RunResult cli(const Daemon& d, std::vector<std::string> args, double timeout_s = 600) {
    return run_cli(d, dir, args, timeout_s);
  }
  DaemonSpec spec(const std::string& name) const { return spec_in(dir, name); }
  std::string path(const std::string& name) const { return (dir / name).string(); }
  void SetUp() override {
    std::ofstream(dir / "test.toml") << config_text();
    write_synthetic_preop(dir);
    write_synthetic_noisy_scan(dir, "scan", kShiftMm);
  }
  void TearDown() override {
    if (HasFailure()) tmp.keep();
  }
};

TEST_F(ImageOnlyE2E, AnImageAloneIsSegmentedRegisteredAndServedThenCorrectedLabelsAreTheOrdinaryPath) {
  const LabelTable table = config::default_label_table();
  const ImageF image = read_scalar_image(dir / "scan_t1.nii.gz");
  const LabelImage truth = read_label_image(dir / "scan_labels.nii.gz");
  // Bad images: all zero; and one that does not show the ventricles (as
  // bright as the brain: no MR contrast the classifier can use).
  ImageF zero = image;
  std::fill(zero.voxels.begin(), zero.voxels.end(), 0.f);
  write_scalar_image(dir / "zero_t1.nii.gz", zero);
  ImageF no_fluid = read_scalar_image(dir / "scan_t1.nii.gz");
  for (std::size_t v = 0; v < truth.voxels.size(); ++v)
    if (truth.voxels[v] == table.find("ventricles")->value) no_fluid.voxels[v] = 100.f;
  write_scalar_image(dir / "no_fluid_t1.nii.gz", test::scanner_image(no_fluid));

  DaemonSpec with_igtl = spec("image-only");
  with_igtl.extra_args = {"--igtl-port", "0"};
  Daemon daemon(with_igtl);
  ASSERT_TRUE(daemon.igtl_port.has_value());
  RunResult r = cli(daemon, {"load-preop", "--image", path("preop_t1.nii.gz"), "--labels",
                             path("preop_labels.nii.gz"), "--wait"});
  ASSERT_EQ(r.code, 0) << r.err << daemon.log();
  test::IgtlReceiver slicer(*daemon.igtl_port, 120s);  // a 3D Slicer stand-in

  // Neither labels nor image: a usage error, nothing sent.
  EXPECT_EQ(cli(daemon, {"push"}).code, 2);

  // The image alone: a non-rigid result (exit 0).
  r = cli(daemon, {"push", "--image", path("scan_t1.nii.gz"), "--id", "or1-img-1", "--wait"});
  ASSERT_EQ(r.code, 0) << r.err << daemon.log();
  const double push_to_result_s = r.seconds;
  const std::string scan_id = r.out.substr(0, r.out.find('\n'));
  r = cli(daemon, {"pull", "--scan", scan_id, "--out", path("pulled"), "--parts",
                   "intraop_labels,segmentation_confidence,field,metrics,timings"});
  ASSERT_EQ(r.code, 0) << r.err;

  // The segmentation on the intraop grid, in the table's values, with a
  // plausible brain: the truth's outline and volume.
  const LabelImage seg = read_label_image(dir / "pulled" / "intraop_labels.nii.gz");
  ASSERT_TRUE(seg.grid.same_geometry(image.grid));
  std::size_t brain = 0, ventricles = 0, truth_brain = 0;
  for (std::size_t v = 0; v < seg.voxels.size(); ++v) {
    const std::uint16_t l = seg.voxels[v];
    ASSERT_TRUE(l == 0 || table.find(l)) << "value " << l << " is not in the label table";
    brain += l != 0;
    ventricles += l == table.find("ventricles")->value;
    truth_brain += truth.voxels[v] != 0;
  }
  EXPECT_NEAR(static_cast<double>(brain) / static_cast<double>(truth_brain), 1.0, 0.05);
  EXPECT_GT(test::outline_dice(seg, truth), 0.95);
  EXPECT_GT(ventricles, 500u);
  // OpenIGTLink: the same segmentation as the label image bs.intraop_labels.
  const auto sent = slicer.next_result();
  const auto seg_message = std::find_if(sent.begin(), sent.end(), [](const test::IgtlReceived& m) {
    return m.device == "bs.intraop_labels";
  });
  ASSERT_NE(seg_message, sent.end());
  ASSERT_NE(seg_message->image(), nullptr);
  EXPECT_EQ(seg_message->image()->GetScalarType(), ::igtl::ImageMessage::TYPE_UINT16);
  ASSERT_EQ(static_cast<std::size_t>(seg_message->image()->GetImageSize()), seg.voxels.size() * 2);
  EXPECT_EQ(std::memcmp(seg_message->image()->GetScalarPointer(), seg.voxels.data(), seg.voxels.size() * 2), 0);
  const ImageF confidence = read_scalar_image(dir / "pulled" / "segmentation_confidence.nii.gz");
  ASSERT_TRUE(confidence.grid.same_geometry(image.grid));
  double mean_confidence = 0;
  for (std::size_t v = 0; v < seg.voxels.size(); ++v) {
    ASSERT_GE(confidence.voxels[v], 0.f);
    ASSERT_LE(confidence.voxels[v], 1.f);
    if (seg.voxels[v]) mean_confidence += confidence.voxels[v] / static_cast<double>(brain);
  }
  EXPECT_GT(mean_confidence, 0.8);
  // The field recovers the known shift (pull-back: u = -shift in the brain).
  const VectorImage3 field = read_vector_image(dir / "pulled" / "field.nii.gz");
  double mean_error_mm = 0;
  for (std::size_t v = 0; v < truth.voxels.size(); ++v)
    if (truth.voxels[v]) mean_error_mm += (field.vectors[v].cast<double>() + kShiftMm).norm() / truth_brain;
  EXPECT_LT(mean_error_mm, 1.0);
  const auto metrics = nlohmann::json::parse(read_file(dir / "pulled" / "metrics.json"));
  EXPECT_TRUE(metrics["segmentation"]["gates"]["passed"].get<bool>()) << metrics["segmentation"].dump();

  // Bad images: refused with the reason reaching the client (exit 5, the
  // daemon's registration of the scan failed), nothing else disturbed.
  r = cli(daemon, {"push", "--image", path("zero_t1.nii.gz"), "--wait"});
  EXPECT_EQ(r.code, 5) << r.err;
  EXPECT_NE(r.err.find("failed in stage segment"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("image is empty"), std::string::npos) << r.err;
  r = cli(daemon, {"push", "--image", path("no_fluid_t1.nii.gz"), "--wait"});
  EXPECT_EQ(r.code, 5) << r.err;
  EXPECT_NE(r.err.find("stage segment"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("ventricular fluid"), std::string::npos) << r.err;

  // A site corrects the segmentation by hand: the labels pushed with the same
  // image and --labels-use exact are used as given, and no derived
  // segmentation is served for them.
  r = cli(daemon, {"push", "--labels", path("scan_labels.nii.gz"), "--image", path("scan_t1.nii.gz"), "--id",
                   "or1-img-1-corrected", "--labels-use", "exact", "--wait"});
  ASSERT_EQ(r.code, 0) << r.err << daemon.log();
  const std::string corrected_id = r.out.substr(0, r.out.find('\n'));
  r = cli(daemon, {"pull", "--scan", corrected_id, "--out", path("corrected"), "--parts", "intraop_labels,field"});
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::exists(dir / "corrected" / "field.nii.gz"));
  EXPECT_FALSE(fs::exists(dir / "corrected" / "intraop_labels.nii.gz"));
  EXPECT_NE(r.err.find("labels_use \"exact\""), std::string::npos) << r.err;
  // The same labels without it (an algorithm's, say) are refined by their
  // image: the segmentation used is served, and metrics.json says so.
  r = cli(daemon, {"push", "--labels", path("scan_labels.nii.gz"), "--image", path("scan_t1.nii.gz"), "--id",
                   "or1-img-1-algorithm", "--wait"});
  ASSERT_EQ(r.code, 0) << r.err << daemon.log();
  const std::string refined_id = r.out.substr(0, r.out.find('\n'));
  r = cli(daemon, {"pull", "--scan", refined_id, "--out", path("refined"), "--parts", "intraop_labels,metrics"});
  ASSERT_EQ(r.code, 0) << r.err;
  const auto refined_metrics = nlohmann::json::parse(read_file(dir / "refined" / "metrics.json"));
  EXPECT_EQ(refined_metrics["given_labels"].value("use", ""), "refine") << refined_metrics["given_labels"].dump();
  EXPECT_TRUE(refined_metrics["given_labels"].value("refined", false)) << refined_metrics["given_labels"].dump();
  EXPECT_TRUE(fs::exists(dir / "refined" / "intraop_labels.nii.gz"));

  // Labels that do not lie where their image does (moved 10 mm: a header or
  // a series mix-up) are refused by the labels-vs-image check. To be refined
  // (the default), they give way to the image's own answer: non-rigid
  // (exit 0), never clean: the caution reaches the client with
  // event.scan.done and stands in metrics.json.
  write_label_image(dir / "moved_labels.nii.gz",
                    resample_nearest(truth, truth.grid, Eigen::Affine3d(Eigen::Translation3d(0, -10, 0)).matrix()));
  r = cli(daemon, {"push", "--labels", path("moved_labels.nii.gz"), "--image", path("scan_t1.nii.gz"), "--id",
                   "or1-img-1-moved-refine", "--wait"});
  ASSERT_EQ(r.code, 0) << r.err << daemon.log();
  EXPECT_NE(r.err.find("CAUTION: the given labels were disregarded"), std::string::npos) << r.err;
  const std::string disregarded_id = r.out.substr(0, r.out.find('\n'));
  r = cli(daemon, {"pull", "--scan", disregarded_id, "--out", path("disregarded"), "--parts", "field,metrics"});
  ASSERT_EQ(r.code, 0) << r.err;
  const auto disregarded_metrics = nlohmann::json::parse(read_file(dir / "disregarded" / "metrics.json"));
  EXPECT_NE(disregarded_metrics.value("caution", "").find("disagree with their image"), std::string::npos)
      << disregarded_metrics.dump();
  EXPECT_TRUE(disregarded_metrics["given_labels"].value("disregarded", false));
  // The pulled field's mean error over the true brain against the known shift.
  const auto field_error_mm = [&](const fs::path& field_path) {
    const VectorImage3 field = read_vector_image(field_path);
    double error_mm = 0;
    for (std::size_t v = 0; v < truth.voxels.size(); ++v)
      if (truth.voxels[v]) error_mm += (field.vectors[v].cast<double>() + kShiftMm).norm() / truth_brain;
    return error_mm;
  };
  EXPECT_LT(field_error_mm(dir / "disregarded" / "field.nii.gz"), 1.0) << "the image's own answer";
  r = cli(daemon, {"list"});  // from scan.list.reply, as a monitor sees it
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find(disregarded_id + "\tdone\t"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\tnonrigid\tCAUTION: the given labels were disregarded"), std::string::npos) << r.out;
  // Used exactly, they are the site's word and are not replaced: exit 4,
  // and the affine-only fallback comes from the image's own segmentation,
  // not from the labels, so it still recovers the known shift.
  r = cli(daemon, {"push", "--labels", path("moved_labels.nii.gz"), "--image", path("scan_t1.nii.gz"), "--id",
                   "or1-img-1-moved", "--labels-use", "exact", "--wait"});
  ASSERT_EQ(r.code, 4) << r.err << daemon.log();
  const std::string moved_id = r.out.substr(0, r.out.find('\n'));
  r = cli(daemon, {"pull", "--scan", moved_id, "--out", path("moved"), "--parts", "field,metrics"});
  ASSERT_EQ(r.code, 0) << r.err;
  const auto moved_metrics = nlohmann::json::parse(read_file(dir / "moved" / "metrics.json"));
  EXPECT_NE(moved_metrics.value("fallback_reason", "").find("disagree with the intraop image"), std::string::npos)
      << moved_metrics.value("fallback_reason", "");
  EXPECT_NE(moved_metrics["affine"].value("fallback_transform", "").find("intraop image's own segmentation"),
            std::string::npos)
      << moved_metrics["affine"].dump();
  EXPECT_LT(field_error_mm(dir / "moved" / "field.nii.gz"), 2.0) << "the fallback follows the moved labels";

  // The image-only scan's parts are served from the store by a restarted daemon.
  EXPECT_EQ(cli(daemon, {"shutdown", "--reason", "test"}).code, 0);
  EXPECT_EQ(daemon.process().wait(60).value_or(-1), 0) << daemon.log();
  Daemon again(spec("image-only-restarted"));
  Client c(again.endpoint);
  ASSERT_NO_THROW(c.wait_ready(300s)) << again.log();
  const auto frames = frames_by_name(c.result(scan_id, {protocol::ResultPart::kIntraopLabels}));
  ASSERT_TRUE(frames.count("intraop_labels")) << again.log();
  EXPECT_EQ(label_image_from_bytes(frames.at("intraop_labels"), "intraop_labels", std::size_t{1} << 30).voxels,
            seg.voxels);
  EXPECT_EQ(cli(again, {"shutdown", "--reason", "test"}).code, 0);
  again.process().wait(60);
  const auto timings = nlohmann::json::parse(read_file(dir / "pulled" / "timings.json"))["intraop"];
  // The timing log has a segment line per round of the segmentation (the
  // first with the head's placement), and they add up to the scan's own
  // segmentation time: a monitor sees the re-match too.
  const auto rounds = nlohmann::json::parse(read_file(dir / "pulled" / "metrics.json"))["segmentation"]["rounds"];
  std::istringstream log_lines(read_file(dir / "store" / "timing.jsonl"));
  std::size_t segment_lines = 0;
  double segment_s = 0;
  for (std::string line; std::getline(log_lines, line);) {
    const auto t = protocol::parse_stage_log_line(line);
    if (t.scan_id != scan_id || t.stage != "segment") continue;
    ++segment_lines;
    segment_s += t.seconds;
  }
  ASSERT_GE(rounds.size(), 2u) << "the first round and a re-match";
  EXPECT_EQ(segment_lines, rounds.size());
  EXPECT_NEAR(segment_s, timings.value("segment", -1.0), 1e-3);
  std::printf("%s\n", nlohmann::json{{"test", "image_only_push"},
                                     {"push_to_result_s_client", push_to_result_s},
                                     {"daemon_intraop_total_s", timings.value("total", -1.0)},
                                     {"daemon_segment_s", timings.value("segment", -1.0)},
                                     {"note", "client-measured push --wait, includes process start; CI load varies"}}
                          .dump()
                          .c_str());
}

// The result of an image-only scan is served from memory and never written
// (fault switch), the daemon is killed: the restarted daemon computes it again
// from the stored image alone, and serves the same segmentation.
TEST_F(ImageOnlyE2E, AnImageOnlyScanIsComputedAgainFromTheStoreAfterACrash) {
  const std::string preop_t1 = read_file(dir / "preop_t1.nii.gz");
  const std::string preop_labels = read_file(dir / "preop_labels.nii.gz");
  const std::string image = read_file(dir / "scan_t1.nii.gz");
  const std::vector<protocol::ResultPart> parts{protocol::ResultPart::kIntraopLabels,
                                                protocol::ResultPart::kSegmentationConfidence};
  std::string scan_id;
  std::map<std::string, std::string> served;
  {
    DaemonSpec first = spec("crash0");
    first.env = {"BRAINSHIFT_INJECT_FAULT=result_write@0#1"};
    Daemon d(first);
    Client c(d.endpoint);
    c.load_preop(preop_t1, preop_labels);
    ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
    EventRecorder events(d.events);
    const protocol::Message pushed = c.push("", image, "img-crash-1");
    ASSERT_EQ(pushed.type(), protocol::MessageType::kScanPushReply) << pushed.header.dump();
    scan_id = protocol::parse_scan_push_reply(pushed).scan_id;
    ASSERT_TRUE(events.wait_for(
        [&](const protocol::Message& m) {
          return m.type() == protocol::MessageType::kEventScanDone &&
                 protocol::parse_scan_done_event(m).scan_id == scan_id;
        },
        300s))
        << d.log();
    served = frames_by_name(c.result(scan_id, parts));
    ASSERT_TRUE(served.count("intraop_labels") && served.count("segmentation_confidence")) << d.log();
    EXPECT_FALSE(fs::exists(dir / "store" / "scans" / scan_id / "result.h5"));
    d.process().signal(SIGKILL);
    d.process().wait(60);
  }
  Daemon d(spec("crash1"));
  Client c(d.endpoint);
  ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();
  std::map<std::string, std::string> again;
  for (int i = 0; i < 600 && !again.count("intraop_labels"); ++i) {  // bounded: 10 min at most
    const protocol::Message reply = c.result(scan_id, parts);
    if (reply.type() == protocol::MessageType::kScanResultReply) again = frames_by_name(reply);
    else std::this_thread::sleep_for(1s);
  }
  ASSERT_TRUE(again.count("intraop_labels")) << d.log();
  EXPECT_NE(d.log().find("re-queueing acknowledged scan " + scan_id), std::string::npos) << d.log();
  EXPECT_TRUE(again.at("intraop_labels") == served.at("intraop_labels")) << "the same segmentation, from the store";
  EXPECT_TRUE(again.at("segmentation_confidence") == served.at("segmentation_confidence"));
  d.process().signal(SIGTERM);
  EXPECT_EQ(d.process().wait(60).value_or(-1), 0) << d.log();
}

}  // namespace
