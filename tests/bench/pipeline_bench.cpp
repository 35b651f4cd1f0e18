// Accuracy and speed of the whole pipeline on the standard phantom suite made
// from the Colin27 atlas, with the default configuration. JSON on stdout.
//   brainshift_pipeline_bench [--config FILE] [--repeat N]
#include <mpi.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <map>

#include "atlas/default_atlas.h"
#include "bench_session.h"
#include "config_file.h"
#include "core/timer.h"
#include "fem/petsc_session.h"
#include "phantom_evaluation.h"

using namespace brainshift;

int main(int argc, char** argv) {
  std::string config_path, atlas_cache = "brainshift-atlas";
  int repeat = 1;
  CLI::App app("brainshift pipeline benchmark: TRE and per-stage seconds on the phantom suite");
  app.add_option("--config", config_path);
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--repeat", repeat, "registrations per case (timing statistics)");
  CLI11_PARSE(app, argc, argv);

  PetscSession petsc;
  if (!bench::drive_from_this_rank()) return 0;
  const PipelineParameters params = bench::parameters(config_path);
  EngineSession session(MPI_COMM_WORLD, params);
  Stopwatch clock;
  DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache);
  session.set_atlas_seconds(clock.lap());
  session.load_preop(PreopInput{std::move(atlas.t1), std::move(atlas.labels)}, nullptr);

  nlohmann::json cases = nlohmann::json::array();
  std::vector<evaluation::CaseResult> results;
  std::vector<double> totals;
  std::map<std::string, std::vector<double>> stages;  // every registration's seconds per stage
  for (const auto& spec : standard_phantom_suite()) {
    for (int r = 0; r < repeat; ++r) {
      auto c = evaluation::evaluate_case(session, spec);
      totals.push_back(c.intraop_total_seconds);
      for (const auto& [stage, seconds] : c.timings["intraop"].items()) stages[stage].push_back(seconds.get<double>());
      if (r == 0) {
        cases.push_back(evaluation::to_json(c));
        results.push_back(std::move(c));
      }
    }
  }
  std::sort(totals.begin(), totals.end());
  nlohmann::json stage_seconds;
  for (auto& [stage, v] : stages) {
    std::sort(v.begin(), v.end());
    stage_seconds[stage] = {{"p50", v[v.size() / 2]}, {"max", v.back()}};
  }
  const auto s = evaluation::summarise(results);
  nlohmann::json out = {
      {"ranks", session.ranks()},
      {"mesh", {{"nodes", session.mesh().node_count()}, {"tets", session.mesh().tet_count()}}},
      {"preop_seconds", session.preop_timings()},
      {"intraop_total_seconds", {{"p50", totals[totals.size() / 2]},
                                 {"p95", totals[std::min(totals.size() - 1, totals.size() * 95 / 100)]},
                                 {"max", totals.back()}}},
      {"intraop_stage_seconds", stage_seconds},
      {"tre_mm", {{"mean", s.mean_mm}, {"worst_case_p95", s.p95_mm}, {"pooled_p95", s.pooled_p95_mm}, {"affine_mean", s.affine_mean_mm},
                  {"uncorrected_mean", s.uncorrected_mean_mm}, {"removed_fraction", s.removed_fraction}}},
      {"cases", cases}};
  std::printf("%s\n", out.dump().c_str());
  return 0;
}
