// Accuracy and robustness on the robustness suite (engine/phantom/robustness_case.h):
// two preop label maps of Colin27, noisy independent intraop segmentations,
// degraded low-field-like intraop T1s, four grid orientations. Each case is
// registered with its intraop T1 and on segmentations alone, and with
// --image-only also from its intraop T1 alone (the automatic segmentation,
// with its Dice against the truth-warped labels). JSON on stdout.
//   brainshift_robustness_bench [--config FILE] [--atlas-cache DIR] [--cases a,b,...] [--image-only]
//                               [--landmark-records FILE] [--check-grid-mm MM]
#include <mpi.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <map>
#include <memory>
#include <set>

#include "bench_session.h"
#include "config_file.h"
#include "core/timer.h"
#include "fem/petsc_session.h"
#include "field/metrics.h"
#include "robustness_evaluation.h"

using namespace brainshift;

namespace {

nlohmann::json summary(const std::vector<evaluation::CaseResult>& runs) {
  std::vector<double> pooled, totals;
  double mean = 0, worst = 0;
  int nonrigid = 0;
  for (const auto& r : runs) {
    pooled.insert(pooled.end(), r.nonrigid_errors_mm.begin(), r.nonrigid_errors_mm.end());
    mean += r.nonrigid_mean_mm;
    worst = std::max(worst, r.nonrigid_max_mm);
    nonrigid += !r.fallback;
    totals.push_back(r.intraop_total_seconds);
  }
  std::sort(totals.begin(), totals.end());
  const double n = std::max<std::size_t>(1, runs.size());
  return {{"cases", runs.size()},
          {"nonrigid_fraction", nonrigid / n},
          {"tre_mean_mm", mean / n},
          {"tre_pooled_p95_mm", pooled.empty() ? 0.0 : percentile(pooled, 95.0)},
          {"tre_worst_landmark_mm", worst},
          {"uncertainty_calibration", evaluation::to_json(evaluation::calibrate(runs))},
          {"intraop_total_seconds", {{"p50", totals.empty() ? 0.0 : totals[totals.size() / 2]},
                                     {"max", totals.empty() ? 0.0 : totals.back()}}}};
}

nlohmann::json brief(const evaluation::CaseResult& r) {
  nlohmann::json j = evaluation::to_json(r);
  j.erase("timings");
  if (!r.predicted_band_mm.empty())
    j["uncertainty_calibration"] = evaluation::to_json(evaluation::calibrate({r}));
  j["intraop_total_seconds"] = r.intraop_total_seconds;
  return j;
}

}  // namespace

int main(int argc, char** argv) {
  std::string config_path, atlas_cache = "brainshift-atlas", records_path;
  std::vector<std::string> only;
  CLI::App app("brainshift robustness benchmark: TRE with and without the intraop T1 on the robustness suite");
  app.add_option("--config", config_path);
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--cases", only, "case names (default: all)")->delimiter(',');
  app.add_option("--landmark-records", records_path, "write per-landmark calibration records (NDJSON) here");
  double check_grid_mm = -1;
  app.add_option("--check-grid-mm", check_grid_mm, "the labels-vs-image check's grid (0: the image's; default: its parameters')");
  bool image_only = false;
  app.add_flag("--image-only", image_only, "also register each case from its intraop image alone");
  CLI11_PARSE(app, argc, argv);

  PetscSession petsc;
  if (!bench::drive_from_this_rank()) return 0;
  PipelineParameters params = bench::parameters(config_path);
  if (check_grid_mm >= 0) params.auto_segmentation.label_image_check.grid_spacing_mm = check_grid_mm;
  const evaluation::RobustnessInputs inputs = evaluation::load_robustness_inputs(atlas_cache);
  std::vector<RobustnessSpec> suite = robustness_suite_cases(only);
  // Cases that share a preop run on one warm session.
  std::stable_sort(suite.begin(), suite.end(), [&](const RobustnessSpec& a, const RobustnessSpec& b) {
    return evaluation::case_anatomy(inputs, a).preop_key < evaluation::case_anatomy(inputs, b).preop_key;
  });
  std::unique_ptr<EngineSession> session;
  std::string warm_key;
  nlohmann::json cases = nlohmann::json::array(), preops = nlohmann::json::object();
  std::vector<evaluation::CaseResult> with_image, labels_only, from_image;
  int refused = 0;
  std::FILE* records = records_path.empty() ? nullptr : std::fopen(records_path.c_str(), "w");
  for (const auto& spec : suite) {
    evaluation::CaseAnatomy anatomy = evaluation::case_anatomy(inputs, spec);
    if (!session || anatomy.preop_key != warm_key) {
      session = std::make_unique<EngineSession>(MPI_COMM_WORLD, params);
      session->load_preop(anatomy.preop, nullptr);
      warm_key = anatomy.preop_key;
      preops[warm_key] = {{"nodes", session->mesh().node_count()}, {"seconds", session->preop_timings()}};
    }
    const auto run = evaluation::run_robustness_case(*session, anatomy, spec, /*with_uncertainty=*/true, image_only);
    const auto write_records = [&](const char* mode, const evaluation::CaseResult& r) {
      if (!records) return;
      for (const auto& l : r.landmark_records)
        std::fprintf(records, "%s\n", nlohmann::json({{"case", spec.phantom.name}, {"mode", mode},
                                                      {"fallback", r.fallback}, {"landmark", l}}).dump().c_str());
    };
    cases.push_back({{"case", spec.phantom.name}, {"preop", warm_key},
                     {"with_image", brief(run.with_image)}, {"labels_only", brief(run.labels_only)}});
    if (image_only) {
      nlohmann::json seg = run.segmentation;
      seg.erase("metrics");
      cases.back()["segmentation"] = seg;
      if (run.image_only) {
        cases.back()["image_only"] = brief(*run.image_only);
        from_image.push_back(*run.image_only);
        const auto cal = evaluation::calibrate({*run.image_only});
        std::fprintf(stderr, "%s: image only %.2f / %.2f mm%s (band %.2f, cover %.2f, rho %.2f), Dice %s\n",
                     spec.phantom.name.c_str(), run.image_only->nonrigid_mean_mm, run.image_only->nonrigid_p95_mm,
                     run.image_only->fallback ? " FALLBACK" : "", cal.mean_band_mm, cal.coverage, cal.spearman,
                     seg.dump().c_str());
        write_records("image", *run.image_only);
      } else {
        ++refused;
        std::fprintf(stderr, "%s: image only refused: %s\n", spec.phantom.name.c_str(), seg.dump().c_str());
      }
    }
    const auto cal_i = evaluation::calibrate({run.with_image}), cal_l = evaluation::calibrate({run.labels_only});
    std::fprintf(stderr,
                 "%s [%s]: image %.2f / %.2f mm%s (band %.2f, cover %.2f, rho %.2f), labels %.2f / %.2f mm%s "
                 "(band %.2f, cover %.2f, rho %.2f)\n",
                 spec.phantom.name.c_str(), warm_key.c_str(), run.with_image.nonrigid_mean_mm,
                 run.with_image.nonrigid_p95_mm, run.with_image.fallback ? " FALLBACK" : "", cal_i.mean_band_mm,
                 cal_i.coverage, cal_i.spearman, run.labels_only.nonrigid_mean_mm, run.labels_only.nonrigid_p95_mm,
                 run.labels_only.fallback ? " FALLBACK" : "", cal_l.mean_band_mm, cal_l.coverage, cal_l.spearman);
    write_records("labels+image", run.with_image);
    write_records("labels", run.labels_only);
    with_image.push_back(run.with_image);
    labels_only.push_back(run.labels_only);
  }
  if (records) std::fclose(records);
  nlohmann::json out = {{"ranks", session ? session->ranks() : 0},
                        {"preops", preops},
                        {"with_image", summary(with_image)},
                        {"labels_only", summary(labels_only)},
                        {"cases", cases}};
  if (image_only) {
    // Refused cases count against the non-rigid fraction: the scan got no answer.
    out["image_only"] = summary(from_image);
    out["image_only"]["refused"] = refused;
    out["image_only"]["nonrigid_fraction"] =
        out["image_only"]["nonrigid_fraction"].get<double>() * static_cast<double>(from_image.size()) /
        static_cast<double>(std::max<std::size_t>(1, from_image.size() + static_cast<std::size_t>(refused)));
  }
  std::printf("%s\n", out.dump().c_str());
  return 0;
}
