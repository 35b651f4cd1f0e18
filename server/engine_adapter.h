#pragma once
// The EnginePort of the shipped daemon: the pipeline's EngineSession (rank 0)
// plus the default atlas and the register-compatible output files.
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
  bool ready() const override { return session_.ready(); }
  const TetMesh& mesh() const override { return session_.mesh(); }
  nlohmann::json preop_timings() const override { return session_.preop_timings(); }
  EngineScanOutput register_scan(const LabelImage& labels, const std::optional<ImageF>& image,
                                 double read_seconds, const std::filesystem::path& scratch_dir,
                                 const StageProgressFn& progress) override;
  int ranks() const override { return session_.ranks(); }
  std::size_t max_image_bytes() const override { return session_.parameters().max_image_bytes; }
  void stop_workers() override { session_.stop_workers(); }

 private:
  EngineSession session_;
};

// Every regular file under dir, by path relative to dir ("models/brain.vtp").
std::map<std::string, std::string> read_tree(const std::filesystem::path& dir);

}  // namespace brainshift::server
