#pragma once
// The EnginePort of the shipped daemon: the pipeline's EngineSession (rank 0)
// plus the default atlas; the outputs come from register's encoder
// (pipeline/scan_outputs.h), images plain for latency, the deferred parts
// made after the scan is announced.
#include <memory>

#include "pipeline/engine_session.h"
#include "server/engine_port.h"

namespace brainshift::server {

class EngineAdapter final : public EnginePort {
 public:
  EngineAdapter(MPI_Comm comm, PipelineParameters params);

  PreopImages load_default_atlas(const std::filesystem::path& cache_dir) override;
  void load_preop(const PreopImages& preop, std::optional<TetMesh> stored_mesh, double atlas_seconds,
                  const StageProgressFn& progress) override;
  const LabelTable& label_table() const override { return session_.parameters().label_table; }
  bool ready() const override { return session_.ready(); }
  const TetMesh& mesh() const override { return session_.mesh(); }
  nlohmann::json preop_timings() const override { return session_.preop_timings(); }
  EngineScanOutput register_scan(const std::optional<LabelImage>& labels, const std::optional<ImageF>& image,
                                 std::optional<GivenLabelsUse> labels_use,
                                 double read_seconds, const StageProgressFn& progress) override;
  int ranks() const override { return session_.ranks(); }
  std::size_t max_image_bytes() const override { return session_.parameters().max_image_bytes; }
  void stop_workers() override { session_.stop_workers(); }
  void render_deferred(const std::string& scan_id, const DeferredOutputFn& add) override;
  std::optional<std::string> itk_field_from_nifti(const std::string& field_nii) override;

 private:
  // What metrics.json, field.h5 and report.png are made from, kept from
  // register_scan to render_deferred (the result is moved, not copied).
  struct Deferred {
    IntraopInput input;
    ScanResult result;
  };
  EngineSession session_;
  std::unique_ptr<Deferred> deferred_;
};

}  // namespace brainshift::server
