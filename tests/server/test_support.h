#pragma once
// Helpers for the server unit tests: small images and
// a test double of the engine (tests only; the shipped daemon uses the real one).
#include <atomic>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>

#include "label_table_file.h"
#include "core/image.h"
#include "core/tet_mesh.h"
#include "server/case_store.h"
#include "server/daemon.h"
#include "server/engine_port.h"
#include "server/server_core.h"
#include "server/server_settings.h"
#include "temp_dir.h"  // tests/support: TempDir

namespace brainshift::test {

// An oblique 1.5 mm grid of n^3 voxels.
Grid3 small_grid(int n);
// A ball of label 1 (radius n/3 voxels) with a label-2 core.
LabelImage ball_labels(int n);
ImageF ramp_image(const Grid3& grid);
TetMesh two_tet_mesh();

// The engine double: load_preop records what it got; register_scan returns
// real NIfTI/VTP/JSON bytes derived from the input so tests can check that
// what comes back over the protocol is exactly what was stored; the files of
// deferred rows (result_outputs.h) follow in render_deferred.
class FakeEngine : public server::EnginePort {
 public:
  server::PreopImages load_default_atlas(const std::filesystem::path&) override;
  void load_preop(const server::PreopImages& preop, std::optional<TetMesh> stored_mesh, double atlas_seconds,
                  const server::StageProgressFn& progress) override;
  const LabelTable& label_table() const override { return table; }
  bool ready() const override { return ready_; }
  const TetMesh& mesh() const override { return mesh_; }
  nlohmann::json preop_timings() const override { return {{"mesh", 0.1}}; }
  // Without labels the double "segments" the image (fake_segmentation) and
  // adds intraop_labels.nii and segmentation_confidence.nii, as the engine does.
  server::EngineScanOutput register_scan(const std::optional<LabelImage>& labels, const std::optional<ImageF>& image,
                                         std::optional<GivenLabelsUse> labels_use, double read_seconds,
                                         const server::StageProgressFn& progress) override;
  int ranks() const override { return 1; }
  std::size_t max_image_bytes() const override { return std::size_t{64} << 20; }
  void stop_workers() override { stopped = true; }
  // report.png = kReportPng when the last scan had an intraop image (once), as
  // the real adapter draws report.png only over an intraop image.
  void render_deferred(const std::string& scan_id, const DeferredOutputFn& add) override;
  // An HDF5 signature and the field's size: the crash recovery's re-encoding.
  std::optional<std::string> itk_field_from_nifti(const std::string& field_nii) override;

  // Expected output files for these inputs (what register_scan returns).
  static std::map<std::string, std::string> files_for(const LabelImage& labels);
  // The double's segmentation of an image alone: the table's brain label where
  // the image exceeds half its maximum, 0 elsewhere (not the engine's method).
  LabelImage fake_segmentation(const ImageF& image) const;

  // A valid 1x1 RGB PNG standing in for report.png.
  static const std::string kReportPng;
  std::function<void()> while_rendering_report;  // called inside render_deferred
  // Called inside render_deferred before the deferred files (metrics.json).
  std::function<void()> while_rendering_deferred;
  // render_deferred calls finished: a test sets a hook once the scan before
  // is done with it (the hook runs on the daemon's worker thread).
  // (shared: tests move-assign a FakeEngine to reset it)
  std::shared_ptr<std::atomic<int>> deferred_renders = std::make_shared<std::atomic<int>>(0);

  LabelTable table = config::default_label_table();  // the shipped labels.toml unless a test sets another
  bool fail_next_scan = false;   // ComputeError from the next register_scan
  // The next scan's result is the affine-only fallback (its kind says so, and
  // its metrics.json).
  bool fallback_next_scan = false;
  bool fail_preop = false;       // InputError from load_preop
  std::optional<GivenLabelsUse> last_labels_use;  // what the last scan's push said
  std::optional<LabelImage> last_labels;          // the labels the last scan was given, as decoded
  std::optional<TetMesh> last_stored_mesh;
  server::PreopImages last_preop;
  std::optional<ImageF> last_scan_image;  // the intraop image of the last register_scan
  bool last_scan_had_labels = false;      // whether the last register_scan was given labels
  int scans_run = 0;
  bool stopped = false;

 private:
  bool ready_ = false;
  bool report_due_ = false;
  std::map<std::string, std::string> deferred_files_;  // of the last scan, for render_deferred
  TetMesh mesh_;
};

// run_daemon (the real sockets and request loop) in a thread; options must
// name a ready_file (endpoints "tcp://127.0.0.1:*" let the OS pick ports).
// Stopped, if still running, when destroyed.
class DaemonThread {
 public:
  DaemonThread(const server::DaemonOptions& options, server::EnginePort& engine);
  ~DaemonThread();
  int join();  // waits until run_daemon returns (e.g. after a shutdown request); its exit code
  const std::string& endpoint() const { return endpoint_; }
  const std::string& events() const { return events_; }

 private:
  std::atomic<bool> stop_{false};
  std::atomic<int> exit_code_{-1};
  std::thread thread_;
  std::string endpoint_, events_;
};

// A started ServerCore over an empty store and the engine double, with no
// preop to warm up: for tests that only send it requests.
struct IdleServer {
  IdleServer();
  TempDir dir;
  server::ServerSettings settings;
  std::unique_ptr<server::CaseStore> store;
  FakeEngine engine;
  std::unique_ptr<server::ServerCore> core;
};

}  // namespace brainshift::test
