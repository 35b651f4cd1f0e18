// brainshiftd's OpenIGTLink gateway end to end: the real daemon on loopback,
// a scan on an oblique LAS grid, and receivers built on the OpenIGTLink
// library's client classes, as 3D Slicer's OpenIGTLinkIF is. Every IMAGE is
// checked against the NIfTI the daemon serves for the same scan, every
// POLYDATA against its .vtp; a receiver that leaves mid-message disturbs
// neither the daemon nor the other receivers.
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <fstream>

#include <nlohmann/json.hpp>

#include "label_table_file.h"
#include "daemon_harness.h"
#include "igtl_receiver.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "synthetic_case.h"

using namespace brainshift;
using namespace brainshift::e2e;
using namespace brainshift::protocol;
using namespace std::chrono_literals;
namespace fs = std::filesystem;
using test::IgtlReceived;
using test::IgtlReceiver;

namespace {

const IgtlReceived& by_device(const std::vector<IgtlReceived>& result, const std::string& device) {
  for (const auto& m : result)
    if (m.device == device) return m;
  throw std::runtime_error("no " + device + " in the result");
}

nlohmann::json status_json(const std::vector<IgtlReceived>& result) {
  return nlohmann::json::parse(result.back().status()->GetStatusString());
}

// The IMAGE's geometry (as Slicer derives it) and voxels against the NIfTI.
void expect_same_image(igtl::ImageMessage& m, const Grid3& grid, const void* voxels, std::size_t bytes,
                       int scalar_type, int components, const std::string& what) {
  SCOPED_TRACE(what);
  int dims[3];
  m.GetDimensions(dims);
  for (int a = 0; a < 3; ++a) EXPECT_EQ(dims[a], grid.dims[a]);
  float spacing[3];
  m.GetSpacing(spacing);
  for (int a = 0; a < 3; ++a) EXPECT_NEAR(spacing[a], grid.spacing_mm()[a], 1e-5);
  EXPECT_EQ(m.GetCoordinateSystem(), igtl::ImageMessage::COORDINATE_RAS);
  // float32 on the wire: positions within ~1e-5 of 100 mm.
  EXPECT_LT((test::igtl_world_from_voxel(m) - grid.world_from_voxel).cwiseAbs().maxCoeff(), 1e-3)
      << test::igtl_world_from_voxel(m) << "\nvs NIfTI\n" << grid.world_from_voxel;
  EXPECT_EQ(m.GetScalarType(), scalar_type);
  EXPECT_EQ(m.GetNumComponents(), components);
  ASSERT_EQ(static_cast<std::size_t>(m.GetImageSize()), bytes);
  EXPECT_EQ(std::memcmp(m.GetScalarPointer(), voxels, bytes), 0) << "voxels differ from the NIfTI";
}

}  // namespace

TEST(E2eIgtl, SlicerStandInGetsEveryResultOnTheObliqueGridAndSurvivesARudeClient) {
  const fs::path dir = fs::temp_directory_path() / ("bs-e2e-igtl-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  write_synthetic_preop(dir);
  write_synthetic_oblique_las_scan(dir, "las1", {2.0, -1.5, 1.0});
  write_synthetic_oblique_las_scan(dir, "las2", {3.0, -0.5, 2.0});
  std::ofstream(dir / "test.toml") << test_config_text(4);

  DaemonSpec spec{dir, dir / "test.toml", dir / "store", "igtl", 0, {}, {"--igtl-port", "0"}};
  Daemon d(spec);
  ASSERT_TRUE(d.igtl_port.has_value()) << "no igtl_port in the ready file";
  Client c(d.endpoint);
  c.load_preop(read_file(dir / "preop_t1.nii.gz"), read_file(dir / "preop_labels.nii.gz"));
  ASSERT_NO_THROW(c.wait_ready(300s)) << d.log();

  IgtlReceiver slicer(*d.igtl_port, 120s);  // connected before any result: nothing queued for it yet
  const Message push =
      c.push(read_file(dir / "las1_labels.nii.gz"), read_file(dir / "las1_t1.nii.gz"), std::string("or1-las1"));
  throw_if_error(push);
  const std::string scan1 = parse_scan_push_reply(push).scan_id;
  const auto result = slicer.next_result();
  std::vector<std::string> devices;
  for (const auto& m : result) devices.push_back(m.device);
  EXPECT_EQ(devices.front(), "bs.field");
  EXPECT_EQ(devices.back(), "bs.status");

  // STATUS: the scan, its kind and (for a fallback) the reason.
  const auto st = status_json(result);
  EXPECT_EQ(st.at("scan_id"), scan1);
  EXPECT_EQ(st.at("client_scan_id"), "or1-las1");
  const std::string kind = st.at("kind");
  EXPECT_TRUE(kind == "nonrigid" || kind == "affine_only_fallback") << kind;
  EXPECT_EQ(st.at("reason").get<std::string>().empty(), kind == "nonrigid");
  EXPECT_EQ(result.back().status()->GetSubCode(), kind == "nonrigid" ? 0 : 1);
  EXPECT_FALSE(st.contains("problems")) << st.dump();
  // The uncertainty map follows its result once stored (a deferred part).
  const auto uncertainty = slicer.next();
  ASSERT_TRUE(uncertainty.has_value()) << "no bs.uncertainty after the result";
  EXPECT_EQ(uncertainty->device, "bs.uncertainty");

  // Against the files the daemon serves for the same scan.
  const auto files = pull_complete(c, scan1,
                                   {ResultPart::kDisplacement, ResultPart::kWarpedImage, ResultPart::kWarpedLabels,
                                    ResultPart::kModels, ResultPart::kUncertainty, ResultPart::kIntraopLabels});
  const VectorImage3 field = vector_image_from_bytes(files.at("displacement"), "displacement", std::size_t{1} << 31);
  // The intraop grid is the oblique LAS one: i points to the patient's left.
  EXPECT_LT(field.grid.world_from_voxel(0, 0), 0.0);
  EXPECT_GT(std::abs(field.grid.world_from_voxel(1, 0)), 0.05);
  expect_same_image(*by_device(result, "bs.field").image(), field.grid, field.vectors.data(),
                    field.vectors.size() * 12, igtl::ImageMessage::TYPE_FLOAT32, 3, "field");
  const ImageF warped = scalar_image_from_bytes(files.at("warped_image"), "warped_image", std::size_t{1} << 31);
  expect_same_image(*by_device(result, "bs.warped_image").image(), warped.grid, warped.voxels.data(),
                    warped.voxels.size() * 4, igtl::ImageMessage::TYPE_FLOAT32, 1, "warped_image");
  const LabelImage labels = label_image_from_bytes(files.at("warped_labels"), "warped_labels", std::size_t{1} << 31);
  expect_same_image(*by_device(result, "bs.warped_labels").image(), labels.grid, labels.voxels.data(),
                    labels.voxels.size() * 2, igtl::ImageMessage::TYPE_UINT16, 1, "warped_labels");
  const ImageF band = scalar_image_from_bytes(files.at("uncertainty"), "uncertainty", std::size_t{1} << 31);
  ASSERT_NE(uncertainty->image(), nullptr);
  expect_same_image(*uncertainty->image(), band.grid, band.voxels.data(), band.voxels.size() * 4,
                    igtl::ImageMessage::TYPE_FLOAT32, 1, "uncertainty");
  EXPECT_GT(*std::max_element(band.voxels.begin(), band.voxels.end()), 0.f) << "the map claims a band in the brain";
  std::size_t models = 0;
  for (const LabelEntry& e : brainshift::config::default_label_table().entries) {
    const auto it = files.find(model_frame_name(e.name));
    if (it == files.end()) continue;
    ++models;
    const TriSurface vtp = read_vtp_bytes(it->second, it->first);
    const std::string device = "bs.model." + short_name_of(e);  // "bs.model.cst" for the tract
    igtl::PolyDataMessage* poly = by_device(result, device).polydata();
    ASSERT_NE(poly, nullptr) << device;
    ASSERT_EQ(static_cast<std::size_t>(poly->GetPoints()->GetNumberOfPoints()), vtp.vertices_mm.size()) << device;
    ASSERT_EQ(static_cast<std::size_t>(poly->GetPolygons()->GetNumberOfCells()), vtp.triangles.size()) << device;
    double worst = 0;
    for (std::size_t i = 0; i < vtp.vertices_mm.size(); ++i) {
      igtlFloat32 p[3];
      poly->GetPoints()->GetPoint(static_cast<unsigned>(i), p);
      worst = std::max(worst, (Eigen::Vector3d(p[0], p[1], p[2]) - vtp.vertices_mm[i]).cwiseAbs().maxCoeff());
    }
    EXPECT_LT(worst, 1e-4) << device << ": POLYDATA points are the .vtp's RAS points";
  }
  EXPECT_GE(models, 2u);  // brain and ventricles at least
  // Labels pushed with their image are refined by it (the default): the
  // engine's segmentation is a label image of its own, as the daemon serves it.
  const bool refined = files.count("intraop_labels") > 0;
  if (refined) {
    const LabelImage seg = label_image_from_bytes(files.at("intraop_labels"), "intraop_labels", std::size_t{1} << 31);
    expect_same_image(*by_device(result, "bs.intraop_labels").image(), seg.grid, seg.voxels.data(),
                      seg.voxels.size() * 2, igtl::ImageMessage::TYPE_UINT16, 1, "intraop_labels");
  }
  EXPECT_EQ(result.size(), 3 + models + (refined ? 1 : 0) + 1);

  // A receiver that leaves in the middle of a message (the latest result is
  // queued for it on connect).
  const int rude = test::raw_igtl_connect(*d.igtl_port);
  char buf[4096];
  std::size_t got = 0;
  while (got < sizeof buf) {
    const ssize_t n = ::recv(rude, buf + got, sizeof buf - got, 0);
    ASSERT_GT(n, 0);
    got += static_cast<std::size_t>(n);
  }
  ::close(rude);
  const StatusReply status = c.status();
  ASSERT_TRUE(status.openigtlink.has_value());
  EXPECT_EQ(status.openigtlink->port, static_cast<std::uint64_t>(*d.igtl_port));
  EXPECT_GE(status.openigtlink->messages_sent, result.size());
  EXPECT_EQ(status.openigtlink->messages_dropped, 0u);

  // The next scan still reaches the steady receiver, and a new one gets it on connect.
  const Message push2 =
      c.push(read_file(dir / "las2_labels.nii.gz"), read_file(dir / "las2_t1.nii.gz"), std::string("or1-las2"));
  throw_if_error(push2);
  const std::string scan2 = parse_scan_push_reply(push2).scan_id;
  EXPECT_EQ(status_json(slicer.next_result()).at("scan_id"), scan2);
  IgtlReceiver late(*d.igtl_port, 60s);
  EXPECT_EQ(status_json(late.next_result()).at("scan_id"), scan2);
  const StatusReply after = c.status();
  ASSERT_TRUE(after.openigtlink.has_value());
  EXPECT_EQ(after.openigtlink->clients, 2u) << "the rude client is gone, the two receivers remain";
  EXPECT_TRUE(d.process().running());
  const std::string log = d.log();
  EXPECT_NE(log.find("OpenIGTLink gateway listening on 127.0.0.1:"), std::string::npos);
  std::error_code ec;
  if (!::testing::Test::HasFailure() && !std::getenv("BRAINSHIFT_KEEP_TEST_FILES")) fs::remove_all(dir, ec);
}

TEST(E2eIgtl, UnsafeOrImpossibleSettingsStopTheStartWithAClearError) {
  const fs::path dir = fs::temp_directory_path() / ("bs-e2e-igtl-cfg-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  auto daemon_argv = [&](const std::string& config_text, std::vector<std::string> extra) {
    const fs::path config = dir / "c.toml";
    std::ofstream(config) << test_config_text(2) << config_text;
    std::vector<std::string> argv = {BRAINSHIFTD_BIN, "--config", config.string(), "--store", (dir / "store").string(),
                                     "--endpoint", "tcp://127.0.0.1:*", "--events", "tcp://127.0.0.1:*"};
    argv.insert(argv.end(), extra.begin(), extra.end());
    return argv;
  };
  // Every interface without saying so.
  auto r = run(daemon_argv("\n[openigtlink]\nenabled = true\nbind = \"0.0.0.0\"\n", {}), dir, 60);
  EXPECT_EQ(r.code, 2) << r.out << r.err;
  EXPECT_NE((r.out + r.err).find("allow_non_loopback"), std::string::npos) << r.out << r.err;
  // Not a port.
  r = run(daemon_argv("", {"--igtl-port", "70000"}), dir, 60);
  EXPECT_EQ(r.code, 2) << r.out << r.err;
  EXPECT_NE((r.out + r.err).find("--igtl-port"), std::string::npos) << r.out << r.err;
  // A port another program holds.
  const int holder = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  inet_pton(AF_INET, "127.0.0.1", &a.sin_addr);
  ASSERT_EQ(::bind(holder, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
  ASSERT_EQ(::listen(holder, 1), 0);
  socklen_t len = sizeof a;
  getsockname(holder, reinterpret_cast<sockaddr*>(&a), &len);
  const std::string port = std::to_string(ntohs(a.sin_port));
  r = run(daemon_argv("", {"--igtl-port", port}), dir, 60);
  ::close(holder);
  EXPECT_EQ(r.code, 1) << r.out << r.err;
  EXPECT_NE((r.out + r.err).find("cannot listen on 127.0.0.1:" + port), std::string::npos) << r.out << r.err;
  std::error_code ec;
  if (!::testing::Test::HasFailure()) fs::remove_all(dir, ec);
}
