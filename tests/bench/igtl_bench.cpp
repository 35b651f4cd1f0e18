// What the OpenIGTLink gateway costs per result (PROTOCOL.md section 16):
// reading a done scan back from a real case store (NIfTI and .vtp decoding)
// and packing it into OpenIGTLink messages, on the gateway's thread. Prints
// JSON; run by hand (docs/PERFORMANCE.md).
#include <malloc.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <random>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "label_table_file.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "server/case_store.h"
#include "server/igtl_gateway.h"

using namespace brainshift;
namespace fs = std::filesystem;

namespace {

// A latitude-longitude sphere of about `vertices` points.
TriSurface sphere(int vertices, double radius_mm) {
  const int rings = std::max(3, static_cast<int>(std::sqrt(vertices / 2.0)));
  const int segments = 2 * rings;
  TriSurface s;
  for (int r = 0; r <= rings; ++r)
    for (int g = 0; g < segments; ++g) {
      const double th = M_PI * r / rings, ph = 2 * M_PI * g / segments;
      s.vertices_mm.emplace_back(radius_mm * std::sin(th) * std::cos(ph), radius_mm * std::sin(th) * std::sin(ph),
                                 radius_mm * std::cos(th));
    }
  for (int r = 0; r < rings; ++r)
    for (int g = 0; g < segments; ++g) {
      const int a = r * segments + g, b = r * segments + (g + 1) % segments;
      s.triangles.push_back({a, a + segments, b});
      s.triangles.push_back({b, a + segments, b + segments});
    }
  return s;
}

std::uint64_t vm_rss_kib() {
  std::ifstream in("/proc/self/status");
  for (std::string line; std::getline(in, line);)
    if (line.rfind("VmRSS:", 0) == 0) return std::stoull(line.substr(6));
  return 0;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"OpenIGTLink gateway cost per result"};
  std::array<int, 3> dims{100, 112, 46};
  int model_vertices = 20000, repeats = 5;
  app.add_option("--dims", dims, "intraop grid (the e2e oblique scan: 100 112 46)");
  app.add_option("--model-vertices", model_vertices, "vertices of each of the four models");
  app.add_option("--repeats", repeats, "runs; the median is reported");
  CLI11_PARSE(app, argc, argv);
  // As brainshiftd runs (server/main.cpp, engine/pipeline/engine_session.cpp):
  // buffers below 32 MB stay on the heap, freed memory is not trimmed.
  mallopt(M_ARENA_MAX, 2);
  mallopt(M_MMAP_THRESHOLD, 32 * 1024 * 1024);
  mallopt(M_TRIM_THRESHOLD, 512 * 1024 * 1024);

  const fs::path dir = fs::temp_directory_path() / ("bs-igtl-bench-" + std::to_string(std::random_device{}()));
  {
    server::CaseStore store(dir);
    Grid3 g;
    g.dims = dims;
    g.world_from_voxel.topLeftCorner<3, 3>() = Eigen::Vector3d(-1.4, 1.4, 2.8).asDiagonal();
    VectorImage3 field(g);
    ImageF image(g);
    LabelImage labels(g);
    for (std::size_t i = 0; i < field.vectors.size(); ++i) {
      field.vectors[i] = Eigen::Vector3f(std::sin(i * 1e-3f), 0.5f, -1.f);
      image.voxels[i] = static_cast<float>(i % 251);
      labels.voxels[i] = static_cast<std::uint16_t>(i % 5);
    }
    const server::PushedScan input{label_image_to_bytes(labels, true), std::nullopt, std::nullopt};
    const auto rec = store.add_scan(input, std::nullopt, server::content_digest(input), "p");
    std::map<std::string, std::string> files{{"field.nii", displacement_field_to_bytes(field, false)},
                                             {"warped_image.nii", scalar_image_to_bytes(image, VoxelType::float32, false)},
                                             {"warped_labels.nii", label_image_to_bytes(labels, false)}};
    for (const char* s : {"brain", "ventricles", "corticospinal_tract", "tumor"})
      files[std::string("models/") + s + ".vtp"] = vtp_bytes(sphere(model_vertices, 50));
    store.save_result(rec.scan_id, files, {});

    const std::uint64_t rss_before = vm_rss_kib();
    std::vector<server::igtl::PackedMessage> latest;  // as the gateway keeps the latest result
    std::vector<double> read_s, pack_s, rss_growth_mib;
    std::map<std::string, std::vector<double>> per_type;
    std::size_t bytes = 0, messages = 0;
    for (int r = 0; r < repeats; ++r) {
      const auto t0 = std::chrono::steady_clock::now();
      const auto content = server::load_igtl_result(store, rec.scan_id, config::default_label_table());
      const auto t1 = std::chrono::steady_clock::now();
      auto packed = server::igtl::encode_result(content);
      const auto t2 = std::chrono::steady_clock::now();
      read_s.push_back(std::chrono::duration<double>(t1 - t0).count());
      pack_s.push_back(std::chrono::duration<double>(t2 - t1).count());
      bytes = messages = 0;
      for (const auto& m : packed) bytes += m.bytes.size(), ++messages;
      latest = std::move(packed);
      rss_growth_mib.push_back((static_cast<double>(vm_rss_kib()) - rss_before) / 1024);
      // Per message type, packed alone.
      const auto ts = server::igtl::time_stamp_from_iso(content.finished_at);
      auto time = [&](const char* type, auto f) {
        const auto a = std::chrono::steady_clock::now();
        f();
        per_type[type].push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - a).count());
      };
      time("field_image", [&] { server::igtl::pack_field("bs.field", *content.field, ts); });
      time("scalar_image", [&] { server::igtl::pack_image("bs.warped_image", *content.warped_image, ts); });
      time("one_polydata", [&] { server::igtl::pack_polydata("bs.model.brain", content.models[0].second, ts); });
    }
    nlohmann::json out{{"bench", "igtl_gateway"},
                       {"dims", dims},
                       {"model_vertices", model_vertices},
                       {"messages", messages},
                       {"megabytes", bytes / 1e6},
                       {"read_from_store_s", median(read_s)},
                       {"pack_s", median(pack_s)},
                       {"total_s", median(read_s) + median(pack_s)},
                       {"vm_rss_growth_mib_per_run", rss_growth_mib}};
    for (auto& [type, v] : per_type) out["pack_one_s"][type] = median(v);
    std::cout << out.dump() << '\n';
  }
  std::error_code ec;
  fs::remove_all(dir, ec);
  return 0;
}
