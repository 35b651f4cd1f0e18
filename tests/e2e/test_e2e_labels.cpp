// A label table of the user's own, end to end through the real binaries: a
// daemon configured with a fifth structure (an arcuate fasciculus) in its
// labels.toml, a preop whose atlas numbers its labels its own way (sent with
// a label map), intraop labels in the same numbering, and the structure's
// model carried, pulled, named in the 3D Slicer scene (from the table the
// daemon serves, labels.get: no local labels.toml) and written by
// `brainshift register` from the same table and the same encoder.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <map>

#include <nlohmann/json.hpp>

#include "daemon_harness.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "process.h"
#include "synthetic_case.h"
#include "temp_dir.h"

using namespace brainshift;
using namespace brainshift::e2e;
namespace fs = std::filesystem;

namespace {

constexpr std::uint16_t kArcuate = 5;  // the daemon's value for the fifth structure
// The sender's atlas numbering: engine value -> sender value.
const std::map<std::uint16_t, std::uint16_t> kSenderValue = {{1, 11}, {2, 12}, {4, 14}, {kArcuate, 25}};
const Eigen::Vector3d kShiftMm(3.0, -2.0, 2.0);

std::string labels_toml_with_arcuate() {
  std::string text = read_file(fs::path(BRAINSHIFT_SOURCE_DIR) / "config" / "labels.toml");
  text += "\n[[label]]\nvalue = 5\nname = \"arcuate_fasciculus\"\nshort_name = \"af\"\ncolour = \"#ff8c00\"\n"
          "role = \"structure\"\nyoungs_modulus_pa = 3000.0\npoisson_ratio = 0.35\n";
  return text;
}

std::string config_text() {
  return R"(label_table = "labels5.toml"

[server]
preop = "none"

[security]
allow_unauthenticated_shutdown = true

[mesh]
cell_size_mm = 7.0
facet_size_mm = 4.0
facet_distance_mm = 1.5
)";
}

// A band of brain in the left hemisphere, beside the ventricles, becomes the
// fifth structure. Returns the centroid of its voxels (RAS mm).
Eigen::Vector3d add_arcuate(LabelImage& labels) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  std::size_t n = 0;
  const auto [nx, ny, nz] = labels.grid.dims;
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const Eigen::Vector3d p = labels.grid.world_from_voxel.topLeftCorner<3, 3>() * Eigen::Vector3d(i, j, k) +
                                  labels.grid.world_from_voxel.block<3, 1>(0, 3);
        const Eigen::Vector3d q = (p - Eigen::Vector3d(-32, 0, 12)).cwiseQuotient(Eigen::Vector3d(6, 20, 6));
        std::uint16_t& v = labels.voxels[(static_cast<std::size_t>(k) * ny + j) * nx + i];
        if (v == 1 && q.squaredNorm() <= 1) {
          v = kArcuate;
          sum += p;
          ++n;
        }
      }
  EXPECT_GT(n, 200u);
  return sum / static_cast<double>(n);
}

LabelImage in_sender_values(LabelImage labels) {
  for (auto& v : labels.voxels)
    if (v) v = kSenderValue.at(v);
  return labels;
}

Eigen::Vector3d mean_vertex(const TriSurface& s) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const auto& p : s.vertices_mm) sum += p.cast<double>();
  return sum / static_cast<double>(s.vertices_mm.size());
}

class LabelTableE2E : public ::testing::Test {
 protected:
  test::TempDir tmp{"e2e-labels"};
  fs::path dir = tmp.path();

  RunResult cli(const Daemon& d, std::vector<std::string> args, double timeout_s = 600) {
    return run_cli(d, dir, args, timeout_s);
  }
  DaemonSpec spec(const std::string& name) const { return spec_in(dir, name); }
  // load-preop with these labels (and extra arguments), push the scan with
  // these labels and wait, pull it with a scene into pulled/: the first
  // command that fails, or the pull.
  RunResult preop_scan_pull(const Daemon& d, const fs::path& preop_labels, std::vector<std::string> preop_extra,
                            const fs::path& scan_labels) {
    std::vector<std::string> load = {"load-preop", "--image", (dir / "preop_t1.nii.gz").string(), "--labels",
                                     preop_labels.string(), "--wait"};
    load.insert(load.end(), preop_extra.begin(), preop_extra.end());
    RunResult r = cli(d, load);
    if (r.code != 0) return r;
    r = cli(d, {"push", "--labels", scan_labels.string(), "--image", (dir / "scan_t1.nii.gz").string(), "--wait"});
    if (r.code != 0) return r;
    const std::string scan_id = r.out.substr(0, r.out.find('\n'));
    // No label table given: the scene is named and coloured by the daemon's (labels.get).
    return cli(d, {"pull", "--scan", scan_id, "--out", (dir / "pulled").string(), "--scene"});
  }
  void TearDown() override {
    if (HasFailure()) tmp.keep();
  }
};

TEST_F(LabelTableE2E, AFifthStructureIsCarriedPulledAndNamedLikeTheOthers) {
  std::ofstream(dir / "labels5.toml") << labels_toml_with_arcuate();
  std::ofstream(dir / "test.toml") << config_text();
  write_synthetic_preop(dir);
  LabelImage preop = read_label_image(dir / "preop_labels.nii.gz");
  const Eigen::Vector3d arcuate_centroid_mm = add_arcuate(preop);
  write_label_image(dir / "preop_labels5.nii.gz", preop);
  write_label_image(dir / "sender_labels.nii.gz", in_sender_values(preop));
  std::ofstream(dir / "map.json") << R"({"v": 1, "structures": {"brain": [11], "ventricles": [12], "tumor": [14],
                                        "arcuate_fasciculus": [25]}})";
  write_synthetic_scan(dir, "scan", kShiftMm);
  write_label_image(dir / "sender_scan_labels.nii.gz", in_sender_values(read_label_image(dir / "scan_labels.nii.gz")));

  Daemon daemon(spec("labels"));
  RunResult r = preop_scan_pull(daemon, dir / "sender_labels.nii.gz", {"--label-table", (dir / "map.json").string()},
                                dir / "sender_scan_labels.nii.gz");
  ASSERT_EQ(r.code, 0) << r.err << daemon.log();

  // Carried like the others: its model, in RAS, moved with the brain.
  const std::string vtp = read_file(dir / "pulled" / "models" / "arcuate_fasciculus.vtp");
  EXPECT_EQ(vtk_space(vtp), "RAS");
  const TriSurface pulled = read_vtp_bytes(vtp, "arcuate_fasciculus.vtp");
  ASSERT_GT(pulled.vertices_mm.size(), 20u);
  EXPECT_LT((mean_vertex(pulled) - (arcuate_centroid_mm + kShiftMm)).norm(), 1.5)
      << mean_vertex(pulled).transpose() << " vs " << (arcuate_centroid_mm + kShiftMm).transpose();
  for (const char* other : {"brain", "ventricles", "tumor"})
    EXPECT_TRUE(fs::exists(dir / "pulled" / "models" / (std::string(other) + ".vtp"))) << other;
  // The warped labels hold it under the daemon's value.
  const LabelImage warped = read_label_image(dir / "pulled" / "warped_labels.nii.gz");
  EXPECT_GT(std::count(warped.voxels.begin(), warped.voxels.end(), kArcuate), 100);
  // Named and coloured from the table in the 3D Slicer scene.
  const std::string scene = read_file(dir / "pulled" / "scene.mrml");
  EXPECT_NE(scene.find("models/arcuate_fasciculus.vtp"), std::string::npos);
  EXPECT_NE(read_file(dir / "pulled" / "labels.ctbl").find("5 arcuate_fasciculus 255 140 0"), std::string::npos);

  // `brainshift register` on the same table, in the daemon's values: the same
  // model, from the same encoder.
  r = run({BRAINSHIFT_BIN, "register", "--config", (dir / "test.toml").string(), "--preop-image",
           (dir / "preop_t1.nii.gz").string(), "--preop-labels", (dir / "preop_labels5.nii.gz").string(),
           "--intraop-labels", (dir / "scan_labels.nii.gz").string(), "--intraop-image",
           (dir / "scan_t1.nii.gz").string(), "--out", (dir / "registered").string()},
          dir, 600);
  ASSERT_EQ(r.code, 0) << r.err;
  const TriSurface registered = read_vtp_bytes(read_file(dir / "registered" / "models" / "arcuate_fasciculus.vtp"));
  ASSERT_EQ(registered.vertices_mm.size(), pulled.vertices_mm.size());
  double worst_mm = 0;
  for (std::size_t i = 0; i < pulled.vertices_mm.size(); ++i)
    worst_mm = std::max(worst_mm, (registered.vertices_mm[i] - pulled.vertices_mm[i]).cast<double>().norm());
  EXPECT_LT(worst_mm, 1e-3);

  // A label map naming a structure the daemon's table lacks is refused, naming it.
  std::ofstream(dir / "bad_map.json") << R"({"v": 1, "structures": {"brain": [11], "liver": [12]}})";
  r = cli(daemon, {"load-preop", "--image", (dir / "preop_t1.nii.gz").string(), "--labels",
                   (dir / "sender_labels.nii.gz").string(), "--label-table", (dir / "bad_map.json").string()});
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("\"liver\" is not in the daemon's label table"), std::string::npos) << r.err;
  EXPECT_EQ(cli(daemon, {"shutdown", "--reason", "test"}).code, 0);
  daemon.process().wait(60);
}

TEST_F(LabelTableE2E, ARenamedParenchymaNamesTheWholeBrainModelEverywhere) {
  std::string table = read_file(fs::path(BRAINSHIFT_SOURCE_DIR) / "config" / "labels.toml");
  const std::string from = "name = \"brain\"";
  ASSERT_NE(table.find(from), std::string::npos);
  table.replace(table.find(from), from.size(), "name = \"cerebrum\"");
  const std::string colour = "colour = \"#28dc3c\"";  // the shipped brain's, just below its name
  ASSERT_EQ(table.find(colour), table.find("name = \"cerebrum\"") + std::string("name = \"cerebrum\"\n").size());
  table.replace(table.find(colour), colour.size(), "colour = \"#c08040\"");
  std::ofstream(dir / "labels5.toml") << table;  // the name config_text() gives
  std::ofstream(dir / "test.toml") << config_text();
  write_synthetic_preop(dir);
  write_synthetic_scan(dir, "scan", kShiftMm);

  Daemon daemon(spec("renamed"));
  // The default pull asks for the table's structures: the whole brain among them.
  const RunResult r = preop_scan_pull(daemon, dir / "preop_labels.nii.gz", {}, dir / "scan_labels.nii.gz");
  ASSERT_EQ(r.code, 0) << r.err << daemon.log();
  EXPECT_EQ(r.err.find("model.cerebrum not available"), std::string::npos) << r.err;
  ASSERT_TRUE(fs::exists(dir / "pulled" / "models" / "cerebrum.vtp"));
  EXPECT_FALSE(fs::exists(dir / "pulled" / "models" / "brain.vtp"));
  EXPECT_GT(read_vtp_bytes(read_file(dir / "pulled" / "models" / "cerebrum.vtp")).vertices_mm.size(), 100u);
  EXPECT_NE(read_file(dir / "pulled" / "scene.mrml").find("models/cerebrum.vtp"), std::string::npos);
  // The scene's names and colours are the daemon's table's, with no local labels.toml given.
  const std::string ctbl = read_file(dir / "pulled" / "labels.ctbl");
  EXPECT_NE(ctbl.find("1 cerebrum 192 128 64"), std::string::npos) << ctbl;
  EXPECT_EQ(ctbl.find("\n1 brain "), std::string::npos) << ctbl;
  EXPECT_EQ(cli(daemon, {"shutdown", "--reason", "test"}).code, 0);
  daemon.process().wait(60);
}

}  // namespace
