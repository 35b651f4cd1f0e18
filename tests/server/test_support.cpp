#include "test_support.h"


#include <algorithm>
#include <chrono>
#include <fstream>
#include <utility>

#include <nlohmann/json.hpp>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "protocol/result_outputs.h"

namespace brainshift::test {
namespace fs = std::filesystem;

Grid3 small_grid(int n) {
  Grid3 g;
  g.dims = {n, n, n};
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = r * 1.5;
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-20, 5, 12.5);
  return g;
}

LabelImage ball_labels(int n) {
  LabelImage l(small_grid(n));
  const double c = (n - 1) / 2.0, r = n / 3.0;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        const double d = std::sqrt((i - c) * (i - c) + (j - c) * (j - c) + (k - c) * (k - c));
        l.at(i, j, k) = d < r / 3 ? 2 : (d < r ? 1 : 0);
      }
  return l;
}

ImageF ramp_image(const Grid3& grid) {
  ImageF im(grid);
  for (std::size_t i = 0; i < im.voxels.size(); ++i) im.voxels[i] = static_cast<float>(i % 97);
  return im;
}

TetMesh two_tet_mesh() {
  TetMesh m;
  m.nodes_mm = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}, {1, 1, 1}};
  m.tets = {{0, 1, 2, 3}, {1, 2, 3, 4}};
  m.tet_labels = {1, 3};
  m.boundary_faces = {{{0, 2, 1}, 0}, {{1, 2, 4}, 2}};
  return m;
}

server::PreopImages FakeEngine::load_default_atlas(const fs::path&) {
  LabelImage labels = ball_labels(10);
  return {ramp_image(labels.grid), labels};
}

void FakeEngine::load_preop(const server::PreopImages& preop, std::optional<TetMesh> stored_mesh, double,
                            const server::StageProgressFn& progress) {
  if (fail_preop) throw InputError("fake: preop refused");
  last_preop = preop;
  last_stored_mesh = stored_mesh;
  progress("mesh", 0.0, 0.0);
  progress("mesh", 1.0, 0.01);
  mesh_ = stored_mesh ? *stored_mesh : two_tet_mesh();
  ready_ = true;
}

std::map<std::string, std::string> FakeEngine::files_for(const LabelImage& labels) {
  VectorImage3 field(labels.grid);
  for (std::size_t i = 0; i < field.vectors.size(); ++i) field.vectors[i] = Eigen::Vector3f(labels.voxels[i], 0.5f, -1.f);
  std::map<std::string, std::string> files;
  // As the daemon's adapter: the field as plain NIfTI; the labels gzipped, as a
  // store written before the daemon stored plain NIfTI holds them.
  files["field.nii"] = displacement_field_to_bytes(field, false);
  files["uncertainty.nii"] = scalar_image_to_bytes(ramp_image(labels.grid), VoxelType::float32, false);
  files["warped_labels.nii.gz"] = label_image_to_bytes(labels, true);
  // The preop T1 warped onto the intraop grid: there is one with or without
  // an intraop image, as with the real engine.
  files["warped_image.nii.gz"] = scalar_image_to_bytes(ramp_image(labels.grid), VoxelType::float32, false);
  files["models/brain.vtp"] =
      "<?xml version=\"1.0\"?>\n<VTKFile type=\"PolyData\" version=\"0.1\"><PolyData><Piece NumberOfPoints=\"0\" "
      "NumberOfPolys=\"0\"></Piece></PolyData></VTKFile>\n";
  files["metrics.json"] = "{\"voxels\": " + std::to_string(labels.voxels.size()) + "}";
  files["timings.json"] = R"({"preop":{"atlas":0,"mesh":0.1,"assemble":0,"factorise":0,"total":0.1},)"
                          R"("intraop":{"read":0,"affine":0,"surface":0,"solve":0,"field":0,"warp":0,"models":0,"total":0},)"
                          R"("mesh":{"nodes":5,"tets":2}})";
  return files;
}

LabelImage FakeEngine::fake_segmentation(const ImageF& image) const {
  LabelImage labels(image.grid);
  float top = 0.f;
  for (float v : image.voxels) top = std::max(top, v);
  for (std::size_t i = 0; i < image.voxels.size(); ++i)
    labels.voxels[i] = image.voxels[i] > 0.5f * top ? table.brain_label() : std::uint16_t{0};
  return labels;
}

server::EngineScanOutput FakeEngine::register_scan(const std::optional<LabelImage>& given,
                                                   const std::optional<ImageF>& image,
                                                   std::optional<GivenLabelsUse> labels_use, double,
                                                   const server::StageProgressFn& progress) {
  ++scans_run;
  last_labels_use = labels_use;
  last_labels = given;
  progress("affine", 0.0, 0.0);
  progress("affine", 1.0, 0.002);
  if (fail_next_scan) {
    fail_next_scan = false;
    throw ComputeError("fake: solver diverged");
  }
  progress("solve", 1.0, 0.003);
  server::EngineScanOutput out;
  // As the engine: an image alone is segmented, and labels with their image
  // are refined by it unless the push said exact (the double always refines).
  const bool segmented = image && (!given || labels_use != GivenLabelsUse::exact);
  const LabelImage labels = given ? *given : fake_segmentation(image.value());
  out.files = files_for(labels);
  if (segmented) {
    out.files["intraop_labels.nii"] = label_image_to_bytes(labels, false);
    const ImageF confidence(labels.grid, 0.9f);
    out.files["segmentation_confidence.nii"] = scalar_image_to_bytes(confidence, VoxelType::float32, false);
  }
  if (fallback_next_scan) {
    fallback_next_scan = false;
    out.result = {protocol::ResultKind::affine_only_fallback, "fake: surface match diverged"};
    out.files["metrics.json"] = R"({"result": "affine_only_fallback", "fallback_reason": "fake: surface match diverged"})";
  }
  out.files["field.h5"] = *itk_field_from_nifti(out.files.at("field.nii"));
  // The deferred rows (result_outputs.h) follow in render_deferred, as the
  // real adapter makes them: the kind travels with scan.done.
  deferred_files_.clear();
  for (auto it = out.files.begin(); it != out.files.end();) {
    const auto part = protocol::part_of_file(it->first);
    if (part && protocol::result_output(*part).deferred) {
      deferred_files_.insert(*it);
      it = out.files.erase(it);
    } else {
      ++it;
    }
  }
  report_due_ = image.has_value();
  last_scan_image = image;
  last_scan_had_labels = given.has_value();
  return out;
}

std::optional<std::string> FakeEngine::itk_field_from_nifti(const std::string& field_nii) {
  return std::string("\x89HDF\r\n\x1a\n", 8) + "fake ITK field of " + std::to_string(field_nii.size()) + " bytes";
}

const std::string FakeEngine::kReportPng(
    "\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\0\x01\0\0\0\x01\x08\x02\0\0\0\x90wS\xde\0\0\0\x0cIDATx\x9c" "c\xf8\xcf\xc0"
    "\0\0\x03\x01\x01\0\xc9\xfe\x92\xef\0\0\0\0IEND\xae" "B`\x82",
    69);

void FakeEngine::render_deferred(const std::string& /*scan_id*/, const DeferredOutputFn& add) {
  if (!deferred_files_.empty() && while_rendering_deferred) while_rendering_deferred();
  for (const auto& [name, bytes] : std::exchange(deferred_files_, {})) add(name, bytes);
  if (report_due_) {
    report_due_ = false;
    if (while_rendering_report) while_rendering_report();
    add("report.png", kReportPng);
  }
  ++*deferred_renders;
}

DaemonThread::DaemonThread(const server::DaemonOptions& options, server::EnginePort& engine) {
  thread_ = std::thread([this, options, &engine] { exit_code_ = server::run_daemon(options, engine, stop_); });
  for (int i = 0; i < 1000 && !fs::exists(options.ready_file) && exit_code_ < 0; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  if (!fs::exists(options.ready_file)) {
    stop_ = true;
    thread_.join();
    throw std::runtime_error("run_daemon did not start");
  }
  std::ifstream in(options.ready_file);
  const nlohmann::json r = nlohmann::json::parse(in);
  endpoint_ = r.at("endpoint").get<std::string>();
  events_ = r.at("events").get<std::string>();
}

DaemonThread::~DaemonThread() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
}

int DaemonThread::join() {
  if (thread_.joinable()) thread_.join();
  return exit_code_;
}

IdleServer::IdleServer() {
  settings.store = dir.path() / "store";
  settings.preop.kind = server::DefaultPreop::Kind::none;
  store = std::make_unique<server::CaseStore>(settings.store);
  core = std::make_unique<server::ServerCore>(settings, *store, engine, [](protocol::Message) {});
  core->start();
}

}  // namespace brainshift::test
