#include "server/engine_adapter.h"

#include <chrono>
#include <fstream>
#include <sstream>

#include "atlas/default_atlas.h"
#include "core/errors.h"
#include "server/hdf5_file.h"

namespace brainshift::server {
namespace fs = std::filesystem;

EngineAdapter::EngineAdapter(MPI_Comm comm, PipelineParameters params) : session_(comm, std::move(params)) {}

PreopImages EngineAdapter::load_default_atlas(const fs::path& cache_dir) {
  DefaultAtlas atlas = load_or_build_default_atlas(cache_dir);
  return PreopImages{std::move(atlas.t1), std::move(atlas.labels)};
}

void EngineAdapter::load_preop(const PreopImages& preop, std::optional<TetMesh> stored_mesh,
                               double atlas_seconds, const StageProgressFn& progress) {
  session_.load_preop(PreopInput{preop.t1, preop.labels}, progress, std::move(stored_mesh));
  session_.set_atlas_seconds(atlas_seconds);
}

EngineScanOutput EngineAdapter::register_scan(const LabelImage& labels, const std::optional<ImageF>& image,
                                              double read_seconds, const fs::path& scratch_dir,
                                              const StageProgressFn& progress) {
  ScanResult result = session_.register_scan(IntraopInput{labels, image}, progress);
  auto& intraop = result.timings["intraop"];
  intraop["read"] = intraop.value("read", 0.0) + read_seconds;
  intraop["total"] = intraop.value("total", 0.0) + read_seconds;
  const fs::path out = scratch_dir / "out";
  const auto t_outputs = std::chrono::steady_clock::now();
  progress("outputs", 0.0, 0.0);
  {
    // write_scan_outputs writes field.h5 through HDF5, which is not thread-safe
    // in this build: the store's lock keeps the socket thread out meanwhile.
    std::lock_guard lock(h5::hdf5_mutex());
    write_scan_outputs(result, image ? &*image : nullptr, out);
  }
  EngineScanOutput output;
  output.files = read_tree(out);
  progress("outputs", 1.0, std::chrono::duration<double>(std::chrono::steady_clock::now() - t_outputs).count());
  output.kind = result.kind == ResultKind::nonrigid ? "nonrigid" : "affine_only_fallback";
  output.fallback_reason = result.fallback_reason;
  output.intraop_seconds = intraop.value("total", 0.0);
  return output;
}

std::map<std::string, std::string> read_tree(const fs::path& dir) {
  std::map<std::string, std::string> files;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    std::ifstream in(e.path(), std::ios::binary);
    std::ostringstream bytes;
    bytes << in.rdbuf();
    if (!in) throw ComputeError("cannot read back " + e.path().string());
    files[fs::relative(e.path(), dir).generic_string()] = bytes.str();
  }
  return files;
}

}  // namespace brainshift::server
