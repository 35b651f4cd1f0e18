// Replays the intensity refinement (registration/intensity_refinement.h) on
// the phantom suite: the pipeline runs once per case without it, then each
// parameter variant refines a copy of that field. TRE, the refinement's
// seconds and the Jacobian of the refined field per case and variant.
//   brainshift_refine_bench [--atlas-cache DIR] [--variant "key=value;key=value"]...
//                           [--blur-slices] [--extra-noise F] [--gamma G] [--invert] [--shuffle-brain] [--repeat N]
//                           [--hospital case,case [--snr S] [--bias B]]
// --hospital replays cases of the hospital-variation suite (phantom/hospital_suite.h,
// labels + image: the algorithmic segmentation and the scanner's image, each
// subject warmed up once) instead of the phantom suite, and splits each
// case's TRE by the landmark's depth below the brain's outline. For
// diagnosis, --snr / --bias give the cases' scanner another SNR or bias
// amplitude (docs/PERFORMANCE.md 9.1).
// A variant holds [intensity] keys of brainshiftd.toml; "" is the defaults.
// --blur-slices smooths the intraop T1 across slices ([1 2 1]/4): a thicker
// slice profile than the phantom's point sampling, as a robustness check.
// The other degradations: --extra-noise adds Gaussian noise of F times the
// brain's 99th percentile; --gamma maps I -> p99 (I / p99)^G (a contrast the
// bias model cannot express); --shuffle-brain permutes the intensities of the
// brain voxels (an image that says nothing: the refinement must not move much).
// --repeat refines each case N times: the seconds are the fastest and the
// median run (the VM is shared; the fastest is the least disturbed).
#include <mpi.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <ctime>
#include <map>
#include <random>

#include "atlas/default_atlas.h"
#include "bench_session.h"
#include "config_file.h"
#include "core/timer.h"
#include "fem/petsc_session.h"
#include "field/metrics.h"
#include "hospital_evaluation.h"
#include "image/resample.h"
#include "phantom/brain_shift_phantom.h"
#include "pipeline/engine_session.h"
#include "registration/boundary_samples.h"
#include "registration/intensity_refinement.h"

using namespace brainshift;

namespace {

struct Case {
  std::string name;
  PhantomCase phantom;
  VectorImage3 field;  // the pipeline's field without the refinement
  ImageF brain_sdf_mm;
  Mask brain_region;
  bool fallback = false;
  const ImageF* preop_t1 = nullptr;
};

// The TRE split by the landmark's depth below the intraop brain outline
// (mm, from the signed distance map): where the refinement helps or not.
std::string depth_split(const Case& c, const std::vector<double>& errors_mm) {
  const double edges[] = {0, 5, 15, 1e9};
  double sum[3] = {0, 0, 0};
  int count[3] = {0, 0, 0};
  const GridSampler sdf(c.brain_sdf_mm.grid);
  for (std::size_t n = 0; n < errors_mm.size() && n < c.phantom.landmarks_intraop_preop_mm.size(); ++n) {
    const double depth = -sdf.linear(c.brain_sdf_mm.voxels, c.phantom.landmarks_intraop_preop_mm[n].first, 0.f);
    for (int b = 0; b < 3; ++b)
      if (depth >= edges[b] && depth < edges[b + 1]) sum[b] += errors_mm[n], ++count[b];
  }
  char out[160];
  std::snprintf(out, sizeof out, "depth <5 %.2f (%d) 5-15 %.2f (%d) >15 %.2f (%d)", count[0] ? sum[0] / count[0] : 0.0,
                count[0], count[1] ? sum[1] / count[1] : 0.0, count[1], count[2] ? sum[2] / count[2] : 0.0, count[2]);
  return out;
}

ImageF blurred_across_slices(const ImageF& in) {
  ImageF out = in;
  const auto& d = in.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        const int a = std::max(0, k - 1), b = std::min(d[2] - 1, k + 1);
        out.at(i, j, k) = 0.25f * in.at(i, j, a) + 0.5f * in.at(i, j, k) + 0.25f * in.at(i, j, b);
      }
  return out;
}

// CPU seconds of the whole process (every thread): unlike the wall clock,
// hardly moved by another job on the shared cores.
double process_cpu_seconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

float brain_p99(const PhantomCase& c) {
  std::vector<float> v;
  for (std::size_t i = 0; i < c.intraop_t1.voxels.size(); ++i)
    if (c.intraop_labels.voxels[i]) v.push_back(c.intraop_t1.voxels[i]);
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(0.99 * v.size()), v.end());
  return v[static_cast<std::size_t>(0.99 * v.size())];
}

void degrade(PhantomCase& c, double noise, double gamma, bool invert, bool shuffle, std::uint64_t seed) {
  const float p99 = brain_p99(c);
  if (invert)
    for (auto& v : c.intraop_t1.voxels) v = std::max(0.f, p99 - v);
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal(0.0, noise * p99);
  for (auto& v : c.intraop_t1.voxels) {
    if (gamma != 1.0) v = static_cast<float>(p99 * std::pow(std::max(0.f, v) / p99, gamma));
    if (noise > 0) v = static_cast<float>(std::abs(v + normal(rng)));
  }
  if (!shuffle) return;
  std::vector<std::size_t> brain;
  for (std::size_t i = 0; i < c.intraop_t1.voxels.size(); ++i)
    if (c.intraop_labels.voxels[i]) brain.push_back(i);
  std::vector<float> values;
  for (auto i : brain) values.push_back(c.intraop_t1.voxels[i]);
  std::shuffle(values.begin(), values.end(), rng);
  for (std::size_t n = 0; n < brain.size(); ++n) c.intraop_t1.voxels[brain[n]] = values[n];
}

std::vector<Eigen::Vector3d> column(const PhantomCase& c, bool preop) {
  std::vector<Eigen::Vector3d> out;
  for (const auto& [x, p] : c.landmarks_intraop_preop_mm) out.push_back(preop ? p : x);
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  std::string atlas_cache = "brainshift-atlas";
  std::vector<std::string> variants;
  bool blur = false, shuffle = false, invert = false;
  double noise = 0, gamma = 1;
  int repeat = 1;
  CLI::App app("replays the intensity refinement on the phantom suite");
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--variant", variants, "[intensity] keys, ';'-separated");
  app.add_flag("--blur-slices", blur);
  app.add_option("--repeat", repeat);
  app.add_option("--extra-noise", noise);
  app.add_option("--gamma", gamma);
  app.add_flag("--shuffle-brain", shuffle);
  app.add_flag("--invert", invert);
  std::vector<std::string> hospital;
  double snr = 0, bias = -1;
  app.add_option("--snr", snr, "hospital cases: the scanner's SNR instead of its own (diagnosis)");
  app.add_option("--bias", bias, "hospital cases: the scanner's bias amplitude instead of its own (diagnosis)");
  app.add_option("--hospital", hospital, "hospital-suite case names instead of the phantom suite")->delimiter(',');
  CLI11_PARSE(app, argc, argv);
  if (variants.empty()) variants.push_back("");

  PetscSession petsc;
  if (!bench::drive_from_this_rank()) return 0;
  PipelineParameters params = config::pipeline_parameters_from_text(config::default_config_text(), "built-in");
  params.intensity.enabled = false;
  const LabelTable& table = params.label_table;
  std::vector<std::uint16_t> tissue;
  for (const auto& e : table.entries)
    if (e.role != LabelRole::cavity) tissue.push_back(e.value);

  std::map<std::string, ImageF> preop_t1;  // each case's preop; stable addresses
  std::vector<Case> cases;
  // Registers the case without the refinement and keeps what a variant needs.
  auto add_case = [&](EngineSession& session, Case c, const ImageF& preop, std::uint64_t seed) {
    if (blur) c.phantom.intraop_t1 = blurred_across_slices(c.phantom.intraop_t1);
    degrade(c.phantom, noise, gamma, invert, shuffle, seed);
    ScanResult r = session.register_scan(IntraopInput{c.phantom.intraop_labels, c.phantom.intraop_t1}, nullptr, true);
    c.fallback = r.kind != ResultKind::nonrigid;
    c.field = std::move(r.pullback_field_mm);
    c.brain_region = outline_mask(c.phantom.intraop_labels);
    c.brain_sdf_mm = prepare_intraop_maps(c.phantom.intraop_labels, c.brain_region, table.brain_label(),
                                          table.cavity_labels().front()).outer_sdf_mm;
    c.preop_t1 = &preop;
    const TreStats t = target_registration_error(c.field, column(c.phantom, false), column(c.phantom, true));
    std::printf("%-34s fem    mean %5.2f p95 %5.2f max %5.2f%s | %s\n", c.name.c_str(), t.mean_mm, t.p95_mm, t.max_mm,
                c.fallback ? " FALLBACK" : "", depth_split(c, t.errors_mm).c_str());
    std::fflush(stdout);
    cases.push_back(std::move(c));
  };
  if (hospital.empty()) {
    EngineSession session(MPI_COMM_WORLD, params);
    DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache);
    session.load_preop(PreopInput{std::move(atlas.t1), std::move(atlas.labels)}, nullptr);
    for (const auto& spec : standard_phantom_suite()) {
      const ImageF& preop = preop_t1.emplace(spec.name, session.preop().t1).first->second;
      Case c;
      c.name = spec.name;
      c.phantom = make_phantom(session.preop().t1, session.preop().labels, spec);
      add_case(session, std::move(c), preop, spec.seed);
    }
  } else {
    const evaluation::AtlasInputs atlas = evaluation::load_atlas_inputs(atlas_cache);
    for (auto spec : hospital_suite()) {
      if (std::find(hospital.begin(), hospital.end(), spec.deformation.name) == hospital.end()) continue;
      if (snr > 0) spec.scanner.snr = snr;
      if (bias >= 0) spec.scanner.bias_amplitude = bias;
      const Subject subject = evaluation::make_named_subject(atlas, spec.subject);
      EngineSession session(MPI_COMM_WORLD, params);
      session.load_preop(PreopInput{subject.t1, subject.labels}, nullptr);
      const ImageF& preop = preop_t1.emplace(spec.deformation.name, subject.t1).first->second;
      Case c;
      c.name = spec.deformation.name;
      c.phantom = make_hospital_case(subject, spec).phantom;
      add_case(session, std::move(c), preop, spec.deformation.seed);
    }
  }
  for (const auto& v : variants) {
    std::string text = "[intensity]\n" + v;
    std::replace(text.begin(), text.end(), ';', '\n');
    const IntensityRefinementParameters p = config::pipeline_parameters_from_text(text, "variant").intensity;
    std::printf("variant \"%s\"\n", v.c_str());
    double sum_mean = 0;
    std::vector<double> pooled, seconds, cpu_seconds;
    for (const auto& c : cases) {
      const IntensityRefinementInput in{c.phantom.intraop_t1, c.phantom.intraop_labels, c.brain_sdf_mm,
                                        *c.preop_t1, tissue, 0};
      VectorImage3 u;
      IntensityRefinementReport rep;
      std::vector<double> runs, cpu;
      for (int r = 0; r < std::max(1, repeat); ++r) {
        u = c.field;
        Stopwatch w;
        const double cpu0 = process_cpu_seconds();
        rep = refine_with_intensity(u, in, p);
        runs.push_back(w.seconds());
        cpu.push_back(process_cpu_seconds() - cpu0);
      }
      std::sort(runs.begin(), runs.end());
      std::sort(cpu.begin(), cpu.end());
      cpu_seconds.push_back(cpu.front());
      seconds.push_back(runs.front());
      const TreStats t = target_registration_error(u, column(c.phantom, false), column(c.phantom, true));
      const JacobianStats jb = jacobian_stats(c.field, &c.brain_region), ja = jacobian_stats(u, &c.brain_region);
      sum_mean += t.mean_mm;
      pooled.insert(pooled.end(), t.errors_mm.begin(), t.errors_mm.end());
      std::printf("%-34s refine mean %5.2f p95 %5.2f max %5.2f | %.3f s it %d | |v| max %.2f mean %.2f | "
                  "rms %.3f -> %.3f | det min %.3f -> %.3f folded %zu -> %zu | s %.3f %.3f %.3f | median %.3f cpu %.3f | R2 %.3f k %.3f l %.2f %s | %s\n",
                  c.name.c_str(), t.mean_mm, t.p95_mm, t.max_mm, seconds.back(), rep.iterations,
                  rep.max_correction_mm, rep.mean_correction_mm, rep.rms_residual_before, rep.rms_residual_after,
                  jb.min_det, ja.min_det, jb.folded_voxels, ja.folded_voxels, rep.sampling_seconds,
                  rep.optimise_seconds, rep.apply_seconds, runs[runs.size() / 2], cpu.front(), rep.explained_variance,
                  rep.data_curvature_per_mm2, rep.smoothing_length_mm, rep.applied ? "" : ("SKIPPED: " + rep.skipped_reason).c_str(), depth_split(c, t.errors_mm).c_str());
      std::fflush(stdout);
    }
    std::sort(seconds.begin(), seconds.end());
    std::sort(cpu_seconds.begin(), cpu_seconds.end());
    std::printf("suite: mean %.3f mm, pooled p95 %.2f mm, fastest seconds p50 %.3f max %.3f, cpu seconds p50 %.3f\n",
                sum_mean / static_cast<double>(cases.size()), percentile(pooled, 95.0), seconds[seconds.size() / 2],
                seconds.back(), cpu_seconds[cpu_seconds.size() / 2]);
  }
  return 0;
}
