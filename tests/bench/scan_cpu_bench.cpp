// Where a scan's time goes, in wall and CPU seconds per stage: a phantom of
// the standard suite registered repeatedly on one warm session, with its
// intraop T1 (labels checked against the image) and on labels alone. CPU
// seconds are the whole process's (every thread) between a stage's start and
// end, reported through the progress callback; they do not depend on what
// else the machine runs, wall seconds do. "field" CPU includes its nested
// "refine". The labels-vs-image check is also timed on its own (thread CPU).
// --image-only: the image alone instead (the automatic segmentation's path).
// JSON on stdout.
//   brainshift_scan_cpu_bench [--atlas-cache DIR] [--case NAME] [--repeat N] [--no-check] [--check-only]
//                             [--check-grid-mm MM] [--check-fit-samples N] [--image-only]
#include <mpi.h>
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <ctime>
#include <map>

#include "atlas/default_atlas.h"
#include "bench_session.h"
#include "core/timer.h"
#include "fem/petsc_session.h"
#include "phantom/brain_shift_phantom.h"
#include "segmentation/label_image_check.h"

using namespace brainshift;

namespace {

double cpu_seconds(clockid_t clock) {
  timespec t{};
  clock_gettime(clock, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// Per stage, every repetition's seconds.
struct StageSamples {
  std::map<std::string, std::vector<double>> wall, cpu;
  std::vector<double> scan_wall, scan_cpu;
  nlohmann::json to_json() const {
    nlohmann::json out;
    for (const auto& [stage, v] : wall) out["wall_p50"][stage] = median(v);
    for (const auto& [stage, v] : cpu) out["cpu_p50"][stage] = median(v);
    out["register_scan"] = {{"wall_p50", median(scan_wall)}, {"cpu_p50", median(scan_cpu)}};
    return out;
  }
};

// A stage reported again within one scan (the image-only path runs the
// stages two or three times) is keyed "<stage>#2", "<stage>#3": each pass's
// share stays apart. The wall seconds are the answer's pass (the timings).
void register_once(EngineSession& session, const ScanInput& scan, StageSamples& s, std::string& kind) {
  std::map<std::string, double> started;
  std::map<std::string, int> seen;
  const ProgressFn progress = [&](const std::string& stage, double fraction, double) {
    const double now = cpu_seconds(CLOCK_PROCESS_CPUTIME_ID);
    if (fraction == 0.0) {
      started[stage] = now;
    } else if (fraction == 1.0 && started.count(stage)) {
      const int n = ++seen[stage];
      s.cpu[n == 1 ? stage : stage + "#" + std::to_string(n)].push_back(now - started[stage]);
    }
  };
  Stopwatch wall;
  const double cpu0 = cpu_seconds(CLOCK_PROCESS_CPUTIME_ID);
  const ScanResult r = session.register_scan(scan, progress, /*defer_quality_metrics=*/true);
  s.scan_cpu.push_back(cpu_seconds(CLOCK_PROCESS_CPUTIME_ID) - cpu0);
  s.scan_wall.push_back(wall.seconds());
  for (const auto& [stage, seconds] : r.timings["intraop"].items())
    if (seconds.is_number()) s.wall[stage].push_back(seconds.get<double>());
  // The segmentation's own split: the head's placement and each round.
  if (r.metrics.contains("segmentation")) {
    const auto& seg = r.metrics["segmentation"];
    if (seg.contains("head_placement") && seg["head_placement"].contains("seconds"))
      s.wall["segment.placement"].push_back(seg["head_placement"]["seconds"].get<double>());
    const auto rounds = seg.value("rounds", nlohmann::json::array());
    for (std::size_t i = 0; i < rounds.size(); ++i)
      if (rounds[i].contains("seconds"))
        s.wall["segment.round" + std::to_string(i + 1)].push_back(rounds[i]["seconds"].get<double>());
  }
  kind = std::string(protocol::to_string(r.kind));
}

}  // namespace

int main(int argc, char** argv) {
  std::string config_path, atlas_cache = "brainshift-atlas", case_name = "vertex_sinking_20mm";
  int repeat = 5;
  bool no_check = false, check_only = false, image_only = false;
  std::size_t check_fit_samples = 0;
  double check_grid_mm = -1;
  CLI::App app("brainshift scan CPU benchmark: wall and CPU seconds per intraop stage");
  app.add_option("--config", config_path);
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--case", case_name, "standard phantom suite case");
  app.add_option("--repeat", repeat, "registrations per mode")->check(CLI::Range(1, 100));
  app.add_flag("--no-check", no_check, "given labels are not checked against the image (to see the check's share)");
  app.add_flag("--check-only", check_only, "time the labels-vs-image check alone (no preop, no registration)");
  app.add_option("--check-fit-samples", check_fit_samples, "the check's EM subsample (default: its parameters')");
  app.add_option("--check-grid-mm", check_grid_mm, "the check's grid spacing (0: the image's; default: its parameters')");
  app.add_flag("--image-only", image_only, "register the image alone (automatic segmentation), no check");
  CLI11_PARSE(app, argc, argv);

  PetscSession petsc;
  if (!bench::drive_from_this_rank()) return 0;
  PipelineParameters params = bench::parameters(config_path);
  if (no_check) params.auto_segmentation.check_given_labels = false;
  // Both for the registrations and for the check timed alone.
  if (check_fit_samples > 0) params.auto_segmentation.label_image_check.fit_samples = check_fit_samples;
  if (check_grid_mm >= 0) params.auto_segmentation.label_image_check.grid_spacing_mm = check_grid_mm;
  DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache);
  const PhantomSpec* spec = nullptr;
  const auto suite = standard_phantom_suite();
  for (const auto& s : suite)
    if (s.name == case_name) spec = &s;
  if (!spec) {
    std::fprintf(stderr, "unknown case %s\n", case_name.c_str());
    return 2;
  }
  const PhantomCase c = make_phantom(atlas.t1, atlas.labels, *spec);
  nlohmann::json out = {{"case", case_name}, {"repeat", repeat},
                        {"grid", {c.intraop_t1.grid.dims[0], c.intraop_t1.grid.dims[1], c.intraop_t1.grid.dims[2]}}};
  EngineSession session(MPI_COMM_WORLD, params);
  if (!check_only) session.load_preop(PreopInput{std::move(atlas.t1), std::move(atlas.labels)}, nullptr);
  if (image_only) {
    ScanInput scan;
    scan.image = c.intraop_t1;
    StageSamples samples;
    std::string kind;
    for (int r = 0; r < repeat; ++r) register_once(session, scan, samples, kind);
    out["image_only"] = samples.to_json();
    out["image_only"]["result"] = kind;
    std::printf("%s\n", out.dump().c_str());
    return 0;
  }
  for (const bool with_image : {true, false}) {
    if (check_only) break;
    ScanInput scan;
    scan.labels = c.intraop_labels;
    if (with_image) scan.image = c.intraop_t1;
    StageSamples samples;
    std::string kind;
    for (int r = 0; r < repeat; ++r) register_once(session, scan, samples, kind);
    out[with_image ? "labels_and_image" : "labels_only"] = samples.to_json();
    out[with_image ? "labels_and_image" : "labels_only"]["result"] = kind;
  }
  // The check alone, on this thread.
  std::vector<double> check_cpu, check_wall;
  nlohmann::json check_metrics;
  for (int r = 0; r < repeat; ++r) {
    segmentation::LabelImageCheckParameters p = params.auto_segmentation.label_image_check;
    p.classifier.max_filled_hole_ml = params.min_resection_cavity_ml;
    Stopwatch wall;
    const double cpu0 = cpu_seconds(CLOCK_THREAD_CPUTIME_ID);
    const auto check = segmentation::check_labels_against_image(c.intraop_t1, c.intraop_labels,
                                                                params.label_table.brain_label(),
                                                                params.label_table.cavity_labels(), p);
    check_cpu.push_back(cpu_seconds(CLOCK_THREAD_CPUTIME_ID) - cpu0);
    check_wall.push_back(wall.seconds());
    check_metrics = check.metrics;
  }
  out["label_image_check"] = {{"cpu_p50", median(check_cpu)}, {"wall_p50", median(check_wall)},
                              {"metrics", check_metrics}};
  std::printf("%s\n", out.dump().c_str());
  return 0;
}
