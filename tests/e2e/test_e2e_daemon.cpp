// brainshiftd end to end: real binaries, real sockets on loopback (ports
// chosen by the OS), a small synthetic head meshed coarsely so the warm-up
// takes seconds. Compares the daemon's results with the one-shot
// `brainshift register` on the same inputs, runs a pusher, a puller and a
// watcher at once, restarts on the same store, and repeats under mpirun -np 2.
#include <gtest/gtest.h>

#include <signal.h>

#include <chrono>
#include <fstream>
#include <set>
#include <thread>

#include <nlohmann/json.hpp>

#include "image/nifti_io.h"
#include "client/exit_codes.h"
#include "mesh/vtk_io.h"
#include "process.h"
#include "temp_dir.h"
#include "protocol/timing_log.h"
#include "synthetic_case.h"

using namespace brainshift;
using namespace brainshift::e2e;
namespace fs = std::filesystem;
using nlohmann::json;

namespace cli = brainshift::cli;

namespace {

const std::vector<std::string> kParts = {"field", "field_h5", "warped_image", "warped_labels",
                                         "models", "metrics", "timings"};

struct Case {
  test::TempDir tmp{"e2e"};
  fs::path dir = tmp.path();
  fs::path config;
};
Case* g_case = nullptr;

std::string config_text() {
  // Coarse mesh: the synthetic head warms up in seconds. "none": the preop is
  // sent by the test (and restored from the store after a restart).
  return R"([server]
preop = "none"
queue_depth = 3

[security]
allow_unauthenticated_shutdown = true  # loopback without CURVE; the tests stop the daemon by request

[mesh]
cell_size_mm = 7.0
facet_size_mm = 4.0
facet_distance_mm = 1.5
)";
}

class Daemon {
 public:
  Daemon(const fs::path& store, bool mpi, const std::string& name) : name_(name) {
    const fs::path ready = g_case->dir / (name + ".ready");
    fs::remove(ready);
    std::vector<std::string> argv;
    if (mpi) argv = {MPIEXEC_BIN, "--allow-run-as-root", "--oversubscribe", "-np", "2"};
    for (const std::string& a : {std::string(BRAINSHIFTD_BIN), std::string("--config"), g_case->config.string(),
                                std::string("--store"), store.string(), std::string("--endpoint"),
                                std::string("tcp://127.0.0.1:*"), std::string("--events"),
                                std::string("tcp://127.0.0.1:*"), std::string("--ready-file"), ready.string()})
      argv.push_back(a);
    process_ = std::make_unique<Process>(argv, g_case->dir / (name + ".out"), g_case->dir / (name + ".err"));
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (!fs::exists(ready) && std::chrono::steady_clock::now() < until && process_->running())
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    if (!fs::exists(ready)) throw std::runtime_error(name + " did not start: " + log());
    const json r = json::parse(read_file(ready));
    endpoint = r.at("endpoint").get<std::string>();
    events = r.at("events").get<std::string>();
  }
  std::string log() const { return read_file(g_case->dir / (name_ + ".err")); }
  Process& process() { return *process_; }

  RunResult client(std::vector<std::string> args, double timeout_s = 300) const {
    std::vector<std::string> argv = {BRAINSHIFT_BIN, "--server", endpoint, "--events", events, "--timeout", "20"};
    argv.insert(argv.end(), args.begin(), args.end());
    return run(argv, g_case->dir, timeout_s);
  }
  json status() const {
    const RunResult r = client({"status", "--json"}, 30);
    if (r.code != 0) throw std::runtime_error("status failed: " + r.err);
    return json::parse(r.out);
  }
  json wait_ready(double timeout_s = 300) const {
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < until) {
      const json s = status();
      if (s.at("state") == "ready") return s;
      std::this_thread::sleep_for(std::chrono::milliseconds(200));
    }
    throw std::runtime_error("not ready in time: " + log());
  }
  // Shutdown request; returns the daemon's exit code.
  std::optional<int> shutdown() {
    const RunResult r = client({"shutdown", "--reason", "test"}, 30);
    EXPECT_EQ(r.code, 0) << r.err;
    return process_->wait(60);
  }

  std::string endpoint, events;

 private:
  std::string name_;
  std::unique_ptr<Process> process_;
};

std::string first_line(const std::string& s) { return s.substr(0, s.find('\n')); }

float max_field_difference(const fs::path& a, const fs::path& b) {
  const VectorImage3 fa = read_vector_image(a), fb = read_vector_image(b);
  EXPECT_TRUE(fa.grid.same_geometry(fb.grid));
  float worst = 0;
  for (std::size_t i = 0; i < fa.vectors.size(); ++i) worst = std::max(worst, (fa.vectors[i] - fb.vectors[i]).cwiseAbs().maxCoeff());
  return worst;
}

class DaemonE2E : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    g_case = new Case;
    g_case->config = g_case->dir / "test.toml";
    std::ofstream(g_case->config) << config_text();
    write_synthetic_preop(g_case->dir);
    write_synthetic_scan(g_case->dir, "scan_a", {4.0, -3.0, 2.5});
    write_synthetic_scan(g_case->dir, "scan_b", {-2.0, 1.0, 3.0});
    write_synthetic_scan(g_case->dir, "scan_c", {1.0, 2.0, -1.5});
    // The one-shot reference for scan A.
    const RunResult r = run({BRAINSHIFT_BIN, "register", "--config", g_case->config.string(), "--preop-image",
                             (g_case->dir / "preop_t1.nii.gz").string(), "--preop-labels",
                             (g_case->dir / "preop_labels.nii.gz").string(), "--intraop-labels",
                             (g_case->dir / "scan_a_labels.nii.gz").string(), "--intraop-image",
                             (g_case->dir / "scan_a_t1.nii.gz").string(), "--out", (g_case->dir / "register_a").string()},
                            g_case->dir, 600);
    ASSERT_EQ(r.code, 0) << r.err;
  }
  static void TearDownTestSuite() {
    // Kept for a post-mortem when anything failed.
    if (::testing::UnitTest::GetInstance()->failed_test_count() > 0) g_case->tmp.keep();
    delete g_case;
  }
  static fs::path path(const std::string& name) { return g_case->dir / name; }

  static std::vector<std::string> pull_args(const std::string& scan, const fs::path& out) {
    std::string parts;
    for (const auto& p : kParts) parts += (parts.empty() ? "" : ",") + p;
    return {"pull", "--scan", scan, "--out", out.string(), "--parts", parts};
  }
  static std::vector<std::string> push_args(const std::string& scan, const std::string& id = "") {
    std::vector<std::string> a = {"push", "--labels", path(scan + "_labels.nii.gz").string(), "--image",
                                  path(scan + "_t1.nii.gz").string(), "--wait"};
    if (!id.empty()) a.insert(a.end(), {"--id", id});
    return a;
  }
};

TEST_F(DaemonE2E, SingleProcessFullCycleConcurrencyAndRestart) {
  const fs::path store = path("store-single");
  std::string scan_a, preop_id;
  std::uint64_t nodes = 0;
  {
    Daemon d(store, false, "single");
    EXPECT_EQ(d.status().at("state"), "idle");
    const RunResult push_early = d.client({"push", "--labels", path("scan_a_labels.nii.gz").string()});
    EXPECT_EQ(push_early.code, cli::kExitError) << "no preop yet: a server error (not_ready)";

    const RunResult load = d.client({"load-preop", "--image", path("preop_t1.nii.gz").string(), "--labels",
                                     path("preop_labels.nii.gz").string(), "--wait"});
    ASSERT_EQ(load.code, 0) << load.err << d.log();
    preop_id = first_line(load.out);
    const json ready = d.wait_ready();
    EXPECT_EQ(ready.at("preop_id"), preop_id);
    nodes = ready.at("mesh").at("nodes").get<std::uint64_t>();
    EXPECT_GT(nodes, 500u);

    Process watcher({BRAINSHIFT_BIN, "--events", d.events, "watch", "--json", "--for", "120"}, path("watch.out"),
                    path("watch.err"));
    std::this_thread::sleep_for(std::chrono::milliseconds(300));  // PUB/SUB: subscribe before the first event

    const RunResult a = d.client(push_args("scan_a", "or-1/a"));
    ASSERT_EQ(a.code, 0) << a.err << d.log();
    scan_a = first_line(a.out);
    EXPECT_EQ(scan_a.rfind("scan-", 0), 0u) << a.out;
    // Same client id, same data: the same scan, nothing new.
    const RunResult again = d.client(push_args("scan_a", "or-1/a"));
    EXPECT_EQ(first_line(again.out), scan_a);

    const RunResult pulled = d.client(pull_args(scan_a, path("pull_a")));
    ASSERT_EQ(pulled.code, 0) << pulled.err;
    for (const char* f : {"field.nii.gz", "field.h5", "warped_image.nii.gz", "warped_labels.nii.gz", "metrics.json",
                          "timings.json", "models/brain.vtp", "models/ventricles.vtp"})
      EXPECT_TRUE(fs::exists(path("pull_a") / f)) << f;
    // 3D Slicer mirrors a model without a frame: the pulled files say RAS.
    for (const char* f : {"models/brain.vtp", "models/ventricles.vtp"})
      EXPECT_NE(read_file(path("pull_a") / f).find("Name=\"SPACE\" NumberOfTuples=\"1\" format=\"ascii\">\n82 65 83 0"),
                std::string::npos) << f;
    // Models carry outward unit normals that Slicer shades with.
    for (const auto& n : read_vtp_normals(read_file(path("pull_a") / "models/brain.vtp"), "brain.vtp"))
      ASSERT_NEAR(n.norm(), 1.0, 2e-4);
    // --scene: a Slicer scene over the pulled folder, with the local images copied in.
    const RunResult scene = d.client({"pull", "--scan", scan_a, "--out", path("pull_scene").string(), "--parts",
                                      "timings", "--scene", "--preop-image", path("preop_t1.nii.gz").string(),
                                      "--intraop-image", path("scan_a_t1.nii.gz").string()});
    ASSERT_EQ(scene.code, 0) << scene.err;
    const std::string mrml = read_file(path("pull_scene") / "scene.mrml");
    for (const char* f : {"field.h5", "warped_image.nii.gz", "warped_labels.nii.gz", "models/brain.vtp",
                          "models/ventricles.vtp", "preop_image.nii.gz", "intraop_image.nii.gz", "labels.ctbl"}) {
      EXPECT_TRUE(fs::exists(path("pull_scene") / f)) << f;
      EXPECT_NE(mrml.find(std::string("fileName=\"") + f + "\""), std::string::npos) << f;
    }
    EXPECT_NE(mrml.find("<GridTransform"), std::string::npos);
    EXPECT_NE(mrml.find("fileName=\"models/brain.vtp\" useCompression=\"1\" coordinateSystem=\"RAS\""), std::string::npos);
    // Named and coloured by the daemon's table (labels.get), here the shipped one.
    EXPECT_NE(read_file(path("pull_scene") / "labels.ctbl").find("1 brain 40 220 60"), std::string::npos);
    // The daemon's field is the one-shot register's field on the same inputs.
    EXPECT_LT(max_field_difference(path("pull_a/field.nii.gz"), path("register_a/field.nii.gz")), 1e-3f);
    EXPECT_EQ(read_file(path("pull_a/warped_labels.nii.gz")).size() > 0, true);
    const auto timings = protocol::parse_timings_json(read_file(path("pull_a/timings.json")));
    EXPECT_GT(timings.intraop.total, 0.0);
    EXPECT_EQ(timings.mesh.nodes, nodes);

    // A pusher, a puller and status requests at once: pulls and status never
    // wait behind the running scans.
    RunResult pusher_b, pusher_c;
    std::thread pusher([&] {
      pusher_b = d.client(push_args("scan_b"));
      pusher_c = d.client(push_args("scan_c"));
    });
    double worst_pull = 0, worst_status = 0;
    int pulls = 0;
    while (pulls < 6) {
      const RunResult p = d.client({"pull", "--scan", scan_a, "--out", path("pull_loop").string(), "--parts", "metrics,timings"});
      EXPECT_EQ(p.code, 0) << p.err;
      worst_pull = std::max(worst_pull, p.seconds);
      const RunResult s = d.client({"status"});
      EXPECT_EQ(s.code, 0);
      worst_status = std::max(worst_status, s.seconds);
      ++pulls;
    }
    pusher.join();
    EXPECT_EQ(pusher_b.code, 0) << pusher_b.err;
    EXPECT_EQ(pusher_c.code, 0) << pusher_c.err;
    std::printf("worst pull %.3f s, worst status %.3f s while scans ran\n", worst_pull, worst_status);
    EXPECT_LT(worst_status, 2.0);

    const RunResult list = d.client({"list"});
    EXPECT_EQ(list.code, 0);
    EXPECT_NE(list.out.find(scan_a), std::string::npos);
    EXPECT_EQ(std::count(list.out.begin(), list.out.end(), '\n'), 3);

    const auto code = d.shutdown();
    ASSERT_TRUE(code.has_value()) << "the daemon did not stop";
    EXPECT_EQ(*code, 0) << d.log();
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    watcher.signal(SIGINT);  // watch stops cleanly on Ctrl-C
    EXPECT_EQ(watcher.wait(10).value_or(-1), 0);

    // One stage line per stage per scan, in the timing-log schema.
    std::set<std::string> scans_with_stages, stages_of_a;
    std::istringstream lines(read_file(path("watch.out")));
    for (std::string line; std::getline(lines, line);) {
      const json j = json::parse(line);
      if (!j.contains("event") || j["event"] != "stage") continue;
      const auto t = protocol::parse_stage_log_line(line);
      if (t.scope == protocol::StageScope::kIntraop) scans_with_stages.insert(t.scan_id);
      if (t.scan_id == scan_a) stages_of_a.insert(t.stage);
    }
    EXPECT_EQ(scans_with_stages.size(), 3u);
    for (const char* s : {"decode", "read", "affine", "solve", "outputs", "store"}) EXPECT_TRUE(stages_of_a.count(s)) << s;
    EXPECT_TRUE(fs::exists(store / "timing.jsonl"));
  }
  // Restart on the same store: the preop comes from the store, not the client.
  {
    Daemon d(store, false, "restart");
    const json ready = d.wait_ready();
    EXPECT_EQ(ready.at("preop_id"), preop_id);
    EXPECT_EQ(ready.at("mesh").at("nodes").get<std::uint64_t>(), nodes) << "the stored mesh is reused";
    const RunResult pulled = d.client(pull_args(scan_a, path("pull_a_again")));
    ASSERT_EQ(pulled.code, 0) << pulled.err;
    for (const auto& e : fs::recursive_directory_iterator(path("pull_a"))) {
      if (!e.is_regular_file()) continue;
      const fs::path rel = fs::relative(e.path(), path("pull_a"));
      EXPECT_EQ(read_file(e.path()), read_file(path("pull_a_again") / rel)) << rel << " changed across the restart";
    }
    // And it still registers new scans with the restored warm state.
    const RunResult b = d.client(push_args("scan_b", "after-restart"));
    EXPECT_EQ(b.code, 0) << b.err;
    EXPECT_EQ(d.shutdown().value_or(-1), 0);
  }
}

TEST_F(DaemonE2E, TwoMpiRanksGiveTheSameField) {
  Daemon d(path("store-mpi"), true, "mpi");
  const RunResult load = d.client({"load-preop", "--image", path("preop_t1.nii.gz").string(), "--labels",
                                   path("preop_labels.nii.gz").string(), "--wait"});
  ASSERT_EQ(load.code, 0) << load.err << d.log();
  EXPECT_EQ(d.wait_ready().at("mpi_ranks").get<int>(), 2);
  const RunResult a = d.client(push_args("scan_a"));
  ASSERT_EQ(a.code, 0) << a.err << d.log();
  const RunResult pulled = d.client({"pull", "--scan", first_line(a.out), "--out", path("pull_mpi").string(), "--parts", "field,timings"});
  ASSERT_EQ(pulled.code, 0) << pulled.err;
  // Two ranks partition the FEM differently: equal up to solver round-off
  // (a hundredth of a millimetre is far below any clinical concern).
  EXPECT_LT(max_field_difference(path("pull_mpi/field.nii.gz"), path("register_a/field.nii.gz")), 1e-2f);
  EXPECT_EQ(d.shutdown().value_or(-1), 0) << d.log();
}

TEST_F(DaemonE2E, SigtermStopsCleanlyAndBadRequestsAreTypedErrors) {
  Daemon d(path("store-signal"), false, "signal");
  // Garbage in a scan: a server error, and the daemon keeps serving.
  std::ofstream(path("garbage.nii")) << std::string(400, 'x');
  const RunResult bad = d.client({"push", "--labels", path("garbage.nii").string()});
  EXPECT_NE(bad.code, 0);
  EXPECT_EQ(d.client({"pull", "--scan", "scan-424242", "--out", path("nothing").string()}).code, cli::kExitError);
  EXPECT_EQ(d.client({"pull", "--scan", "x", "--out", path("nothing").string(), "--parts", "bogus"}).code,
            cli::kExitUsage);
  EXPECT_EQ(d.status().at("state"), "idle");
  d.process().signal(SIGTERM);
  const auto code = d.process().wait(30);
  ASSERT_TRUE(code.has_value()) << "SIGTERM did not stop the daemon";
  EXPECT_EQ(*code, 0) << d.log();
}

TEST(ClientE2E, UnreachableServerTimesOutWithExitCode3) {
  const test::TempDir dir("e2e-client");
  const RunResult r =
      run({BRAINSHIFT_BIN, "--server", "tcp://127.0.0.1:9", "--timeout", "0.5", "status"}, dir.path(), 30);
  EXPECT_EQ(r.code, cli::kExitUnreachable) << r.err;
  EXPECT_NE(r.err.find("no reply"), std::string::npos) << r.err;
  EXPECT_LT(r.seconds, 5.0);
  EXPECT_EQ(run({BRAINSHIFT_BIN, "push"}, dir.path(), 30).code, cli::kExitUsage);
}

}  // namespace
