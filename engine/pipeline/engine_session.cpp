#include "pipeline/engine_session.h"

#include <malloc.h>

#include "core/errors.h"
#include "core/fault_injection.h"
#include "image/intensity_offset.h"
#include "pipeline/mpi_commands.h"
#include "pipeline/labels_with_image.h"
#include "pipeline/prepare_stage.h"
#include "pipeline/uncertainty_stage.h"
#include "pipeline/warm_state.h"
#include "protocol/stage_names.h"

namespace brainshift {

namespace {

// Every scan allocates the same few dozen images of 4-16 MB and frees them
// again. By default glibc serves those with fresh mmap()s, and the kernel
// zeroes every page on first touch (measured: ~9 % of a registration's CPU in
// clear_page). Keeping them on the heap lets the next scan reuse the memory.
void keep_scan_buffers_on_the_heap() {
  static const bool done = [] {
    mallopt(M_MMAP_THRESHOLD, 32 * 1024 * 1024);  // glibc's maximum
    mallopt(M_TRIM_THRESHOLD, 512 * 1024 * 1024);
    return true;
  }();
  (void)done;
}

// The preop timings count the atlas (reading or building the preop images)
// in their total; set again, the old figure is taken out first.
void with_atlas_seconds(nlohmann::json& timings, double seconds) {
  const std::string atlas(protocol::stages::kAtlas), total(protocol::stages::kTotal);
  timings[total] = timings.value(total, 0.0) - timings.value(atlas, 0.0) + seconds;
  timings[atlas] = seconds;
}

}  // namespace

EngineSession::EngineSession(MPI_Comm comm, PipelineParameters params)
    : comm_(comm), params_(std::move(params)) {
  params_.label_table.validate();
  (void)injected_fault();  // a malformed BRAINSHIFT_INJECT_FAULT fails here, at start-up
  keep_scan_buffers_on_the_heap();
}

EngineSession::~EngineSession() {
  // Workers must leave their loop before MPI/PETSc finalise.
  try {
    stop_workers();
  } catch (...) {
  }
}

void EngineSession::load_preop(PreopInput input, const ProgressFn& progress,
                               std::optional<TetMesh> stored_mesh) {
  const double lifted_by = lift_negative_intensities(input.t1);
  // Built aside and swapped in: a failed load keeps the previous warm state.
  auto next = build_warm_state(comm_, std::move(input), params_, progress, std::move(stored_mesh));
  with_atlas_seconds(next->timings, atlas_seconds_);
  warm_ = std::move(next);
  preop_lifted_by_ = lifted_by;
}

bool EngineSession::ready() const { return warm_ != nullptr; }

const TetMesh& EngineSession::mesh() const {
  if (!warm_) throw ComputeError("no preop state is loaded");
  return warm_->fem.mesh();
}

const PreopInput& EngineSession::preop() const {
  if (!warm_) throw ComputeError("no preop state is loaded");
  return warm_->preop;
}

nlohmann::json EngineSession::preop_timings() const {
  return warm_ ? warm_->timings : nlohmann::json::object();
}

void EngineSession::set_atlas_seconds(double seconds) {
  atlas_seconds_ = seconds;
  if (warm_) with_atlas_seconds(warm_->timings, seconds);
}

namespace {

// The input with its image lifted (image/intensity_offset.h) when it holds
// negative values, else nullopt (the caller keeps its own, no copy).
std::optional<IntraopInput> lifted(const IntraopInput& input, double* by) {
  *by = 0;
  if (!input.t1 || !has_negative_intensities(*input.t1)) return std::nullopt;
  IntraopInput copy = input;
  *by = lift_negative_intensities(*copy.t1);
  return copy;
}

std::optional<ScanInput> lifted(const ScanInput& scan, double* by) {
  *by = 0;
  if (!scan.image || !has_negative_intensities(*scan.image)) return std::nullopt;
  ScanInput copy = scan;
  *by = lift_negative_intensities(*copy.image);
  return copy;
}

}  // namespace

// What was lifted, in the scan's metrics (PROTOCOL.md 5.4 "intensity_lift").
void EngineSession::report_lift(ScanResult& result, double intraop_by) const {
  if (intraop_by > 0 || preop_lifted_by_ > 0)
    result.metrics["intensity_lift"] = {{"intraop", intraop_by}, {"preop_t1", preop_lifted_by_}};
}

ScanResult EngineSession::register_scan(const IntraopInput& given, const ProgressFn& progress,
                                        bool defer_quality_metrics) {
  if (!warm_) throw InputError("no preop state is loaded: load the preop images first");
  double by = 0;
  const auto lifted_input = lifted(given, &by);
  ScanResult result = run_intraop(*warm_, lifted_input ? *lifted_input : given, params_, progress, !defer_quality_metrics);
  report_lift(result, by);
  return result;
}

ScanResult EngineSession::register_scan(const ScanInput& given, const ProgressFn& progress,
                                        bool defer_quality_metrics) {
  if (!warm_) throw InputError("no preop state is loaded: load the preop images first");
  double by = 0;
  const auto lifted_scan = lifted(given, &by);
  const ScanInput& scan = lifted_scan ? *lifted_scan : given;
  ScanResult result = register_scan_as_given(scan, progress, defer_quality_metrics);
  report_lift(result, by);
  return result;
}

ScanResult EngineSession::register_scan_as_given(const ScanInput& scan, const ProgressFn& progress,
                                                 bool defer_quality_metrics) {
  if (!scan.labels && !scan.image) throw InputError("a scan needs an intraop image, labels, or both");
  if (scan.labels && (!scan.image || !params_.auto_segmentation.check_given_labels))
    return register_given_labels(*warm_, IntraopInput{*scan.labels, scan.image, scan.read_seconds}, params_, progress,
                                 !defer_quality_metrics);
  ScanResult result =
      scan.labels ? register_labels_with_image(*warm_, IntraopInput{*scan.labels, scan.image, scan.read_seconds}, params_,
                                               scan.labels_use.value_or(params_.auto_segmentation.given_labels),
                                               progress, !defer_quality_metrics)
                  : register_image_only(*warm_, *scan.image, scan.read_seconds, params_, progress, !defer_quality_metrics);
  result.timings["preop"] = preop_timings();
  return result;
}

void EngineSession::add_quality_metrics(const IntraopInput& given, ScanResult& result,
                                        const ProgressFn& progress) const {
  if (!warm_) throw InputError("no preop state is loaded: load the preop images first");
  double by = 0;
  const auto input = lifted(given, &by);
  brainshift::add_quality_metrics(*warm_, input ? *input : given, params_, result, progress);
}

void EngineSession::add_uncertainty(const IntraopInput& given, ScanResult& result, const ProgressFn& progress) {
  if (!warm_) throw InputError("no preop state is loaded: load the preop images first");
  double by = 0;
  const auto input = lifted(given, &by);
  brainshift::add_uncertainty(*warm_, input ? *input : given, params_, result, progress);
}

void EngineSession::stop_workers() {
  if (workers_stopped_) return;
  workers_stopped_ = true;
  mpi_channel::broadcast_command(comm_, mpi_channel::Command::stop);
}

int EngineSession::ranks() const {
  int size = 1;
  MPI_Comm_size(comm_, &size);
  return size;
}

void run_worker_loop(MPI_Comm comm) {
  FemCluster fem(comm);
  for (;;) {
    switch (mpi_channel::receive_command(comm)) {
      case mpi_channel::Command::stop: return;
      case mpi_channel::Command::load: fem.serve_load(); break;
      case mpi_channel::Command::solve: fem.serve_solve(); break;
    }
  }
}

}  // namespace brainshift
