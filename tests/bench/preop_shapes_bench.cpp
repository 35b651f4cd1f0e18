// The preop warm-up (mesh + FEM assembly and factorisation + models) on label
// maps of heads other than the atlas (tests/mesh/head_shapes.h), at the
// configured (default) mesh size, against the target of at most 30 s. JSON
// on stdout, one object per head: wall and CPU seconds, the preop timings and
// the meshing report (exudation steps and budget, min dihedral angle).
//   brainshift_preop_shapes_bench [--config FILE] [--atlas-cache DIR] [--cases a,b]
//       [--mesh-only] [--exude-steps-per-vertex X]
// --mesh-only meshes without the FEM; a huge --exude-steps-per-vertex (1e12)
// is exudation without a budget, to see whether it runs away (run it under
// `timeout`).
#include <mpi.h>
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <cstdio>

#include "atlas/default_atlas.h"
#include "bench_session.h"
#include "core/timer.h"
#include "fem/petsc_session.h"
#include "head_shapes.h"
#include "mesh/label_mesher.h"

using namespace brainshift;

namespace {

double cpu_seconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

double load_average() {
  double load[1] = {0};
  return getloadavg(load, 1) == 1 ? load[0] : -1;
}

nlohmann::json mesh_only(const LabelImage& labels, const PipelineParameters& params) {
  MeshingParameters p = params.meshing;
  const LabelTable& table = params.label_table;
  p.cavity_labels = table.cavity_labels();
  p.default_tissue_label = table.brain_label();
  for (const auto l : table.resectable_labels())
    for (const auto v : labels.voxels)
      if (v == l) {
        p.interface_labels.push_back(l);
        break;
      }
  MeshingStats s;
  const TetMesh mesh = mesh_label_image(labels, p, &s);
  return {{"nodes", mesh.node_count()},       {"tets", mesh.tet_count()},
          {"refine_seconds", s.seconds_refine}, {"optimise_seconds", s.seconds_optimise},
          {"exude_steps", s.exude_steps},     {"exude_budget", s.exude_budget},
          {"exude_budget_hit", s.exude_budget_hit}, {"slivers_before", s.slivers_before},
          {"slivers_after", s.slivers_after}, {"min_dihedral_before_deg", s.min_dihedral_before_deg},
          {"min_dihedral_after_deg", s.min_dihedral_after_deg}, {"vertex_cap", s.vertex_cap}};
}

}  // namespace

int main(int argc, char** argv) {
  std::string config_path, atlas_cache = "brainshift-atlas";
  std::vector<std::string> only;
  bool only_mesh = false;
  double steps_per_vertex = -1;
  CLI::App app("brainshift preop warm-up on other heads");
  app.add_option("--config", config_path);
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--cases", only, "head names (default: all)")->delimiter(',');
  app.add_flag("--mesh-only", only_mesh);
  app.add_option("--exude-steps-per-vertex", steps_per_vertex);
  CLI11_PARSE(app, argc, argv);

  PetscSession petsc;
  if (!bench::drive_from_this_rank()) return 0;
  PipelineParameters params = bench::parameters(config_path);
  if (steps_per_vertex >= 0) params.meshing.exude_steps_per_vertex = steps_per_vertex;
  const DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache);
  const LabelImage atlas_labels = atlas_labels_for(atlas.labels, params.label_table);
  const test::HeadLabels l = test::head_labels_of(params.label_table);
  const std::vector<std::string> names = only.empty() ? test::head_case_names() : only;
  nlohmann::json out = nlohmann::json::array();
  for (const auto& name : names) {
    const test::HeadCase head = test::make_head_case(name, atlas_labels, l);
    const double load = load_average();
    Stopwatch wall;
    const double cpu0 = cpu_seconds();
    nlohmann::json row = {{"head", name}, {"load_average_1min", load}};
    if (only_mesh) {
      row["mesh"] = mesh_only(head.labels, params);
    } else {
      EngineSession session(MPI_COMM_WORLD, params);
      // The atlas T1 stays as it is: the warm-up meshes and solves on the labels.
      session.load_preop(PreopInput{atlas.t1, head.labels}, nullptr);
      row["nodes"] = session.mesh().node_count();
      row["tets"] = session.mesh().tet_count();
      row["preop"] = session.preop_timings();
    }
    row["wall_seconds"] = wall.seconds();
    row["cpu_seconds_rank0"] = cpu_seconds() - cpu0;
    std::fprintf(stderr, "%s: %.1f s wall, %.1f s CPU\n", name.c_str(), row["wall_seconds"].get<double>(),
                 row["cpu_seconds_rank0"].get<double>());
    out.push_back(row);
  }
  std::printf("%s\n", out.dump(1).c_str());
  return 0;
}
