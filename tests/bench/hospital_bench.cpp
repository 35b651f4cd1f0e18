// The hospital-variation suite (engine/phantom/hospital_suite.h): other heads,
// large and steep deformations, several scanners, segmentations made by an
// algorithm from the intraop image. Each case is registered in the modes
// asked for (labels+image, labels, image). Output: one JSON record per line
// as it goes (a "preop" record per subject warm-up, a "case" record per
// case), so a run stopped by a time limit keeps what it finished;
// --summarise FILE turns such lines (of one or several runs) into the suite's
// document. hospital_bench.sh runs each subject under a time limit.
//   brainshift_hospital_bench [--config FILE] [--atlas-cache DIR] [--cases a,b] [--subjects s,t]
//                             [--modes labels+image,labels,image]
//   brainshift_hospital_bench --summarise records.ndjson [--cases ...] [--subjects ...]
#include <mpi.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <set>

#include "bench_session.h"
#include "config_file.h"
#include "fem/petsc_session.h"
#include "hospital_evaluation.h"
#include "image/nifti_io.h"

using namespace brainshift;

namespace {

constexpr std::uint64_t kReseedStride = 1000;

void emit(const nlohmann::json& record) {
  std::printf("%s\n", record.dump().c_str());
  std::fflush(stdout);
}

std::vector<HospitalCaseSpec> selected(const std::vector<std::string>& cases, const std::vector<std::string>& subjects) {
  std::vector<HospitalCaseSpec> suite = hospital_suite();
  const std::set<std::string> want_cases(cases.begin(), cases.end()), want_subjects(subjects.begin(), subjects.end());
  std::erase_if(suite, [&](const HospitalCaseSpec& s) {
    return (!want_cases.empty() && !want_cases.count(s.deformation.name)) ||
           (!want_subjects.empty() && !want_subjects.count(s.subject));
  });
  // Cases of one subject run on one warm session.
  std::stable_sort(suite.begin(), suite.end(),
                   [](const HospitalCaseSpec& a, const HospitalCaseSpec& b) { return a.subject < b.subject; });
  return suite;
}

// Each case once per SNR (none given: the suite as it is); the seed is kept, so
// the cases differ by their noise's level only.
std::vector<HospitalCaseSpec> with_snr_sweep(const std::vector<HospitalCaseSpec>& suite, const std::vector<double>& snrs) {
  if (snrs.empty()) return suite;
  std::vector<HospitalCaseSpec> out;
  for (const auto& s : suite)
    for (double snr : snrs) {
      HospitalCaseSpec c = s;
      c.scanner.snr = snr;
      char suffix[32];
      std::snprintf(suffix, sizeof suffix, "_snr%g", snr);
      c.deformation.name += suffix;
      out.push_back(c);
    }
  return out;
}

// --reseed K: every case and subject drawn again from other seeds (another
// head's reshaping, another deformation's detail and noise; the same kinds
// of case), named CASE_reseedK: cases the engine was never tuned on.
std::vector<HospitalCaseSpec> reseeded(std::vector<HospitalCaseSpec> suite, std::uint64_t k) {
  if (k == 0) return suite;
  for (auto& c : suite) {
    c.deformation.seed += kReseedStride * k;
    c.deformation.name += "_reseed" + std::to_string(k);
  }
  return suite;
}

// Every selected case without a record is marked unfinished, with its
// subject's warm-up status.
int summarise(const std::string& path, const std::vector<HospitalCaseSpec>& suite, const std::vector<std::string>& modes) {
  std::ifstream in(path);
  if (!in) {
    std::fprintf(stderr, "cannot read %s\n", path.c_str());
    return 2;
  }
  std::vector<nlohmann::json> records;
  std::set<std::string> done_cases, warm_subjects;
  std::map<std::string, std::string> subject_notes;
  for (std::string line; std::getline(in, line);) {
    if (line.empty() || line[0] != '{') continue;
    nlohmann::json r = nlohmann::json::parse(line, nullptr, false);
    if (r.is_discarded()) continue;
    if (r.value("record", "") == "case") done_cases.insert(r.value("case", ""));
    if (r.value("record", "") == "preop" && r.value("status", "") == "ready") warm_subjects.insert(r.value("subject", ""));
    if (r.value("record", "") == "preop" && r.contains("note")) subject_notes[r.value("subject", "")] = r["note"];
    records.push_back(r);
  }
  for (const auto& s : suite) {
    if (done_cases.count(s.deformation.name)) continue;
    std::string why = warm_subjects.count(s.subject) ? "the case did not finish within the time limit"
                                                     : "the preop warm-up did not finish";
    if (subject_notes.count(s.subject)) why += ": " + subject_notes[s.subject];
    records.push_back(evaluation::unfinished_case_record(s, why));
  }
  std::printf("%s\n", evaluation::summarise_records(records, modes).dump(1).c_str());
  return 0;
}

// Meshes, assembles and factorises the subject's preop; a failure is a record.
bool warm_up(std::unique_ptr<EngineSession>& session, const PipelineParameters& params, const Subject& subject) {
  session = std::make_unique<EngineSession>(MPI_COMM_WORLD, params);
  const auto t0 = std::chrono::steady_clock::now();
  try {
    session->load_preop({subject.t1, subject.labels}, nullptr);
  } catch (const std::exception& e) {
    emit({{"record", "preop"}, {"subject", subject.name}, {"status", "failed"}, {"note", e.what()}});
    session.reset();
    return false;
  }
  emit({{"record", "preop"}, {"subject", subject.name}, {"status", "ready"}, {"nodes", session->mesh().node_count()},
        {"warmup_seconds", std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count()},
        {"timings", session->preop_timings()}});
  return true;
}

void write_subject(const std::filesystem::path& dir, const Subject& s) {
  const auto d = dir / "subjects" / s.name;
  std::filesystem::create_directories(d);
  write_scalar_image(d / "preop_t1.nii.gz", s.t1);
  write_label_image(d / "preop_labels.nii.gz", s.labels);
  std::ofstream(d / "subject.json") << s.description.dump(1) << "\n";
}

// The case as a site would receive it (image, segmentation), its truth
// (noise-free labels, the pull-back field) and the landmarks.
void write_case(const std::filesystem::path& dir, const HospitalCaseSpec& spec, const HospitalCase& c) {
  const auto d = dir / "cases" / spec.deformation.name;
  std::filesystem::create_directories(d);
  write_scalar_image(d / "intraop_image.nii.gz", c.phantom.intraop_t1);
  write_label_image(d / "intraop_labels.nii.gz", c.phantom.intraop_labels);
  write_label_image(d / "true_intraop_labels.nii.gz", c.true_labels);
  write_displacement_field(d / "true_pullback_mm.nii.gz", c.phantom.true_pullback_mm);
  nlohmann::json landmarks = nlohmann::json::array();
  for (const auto& [x, p] : c.phantom.landmarks_intraop_preop_mm)
    landmarks.push_back({{"intraop_mm", {x.x(), x.y(), x.z()}}, {"preop_mm", {p.x(), p.y(), p.z()}}});
  std::ofstream(d / "landmarks.json") << landmarks.dump() << "\n";
  std::ofstream(d / "case.json") << nlohmann::json({{"subject", spec.subject}, {"description", c.description}}).dump(1) << "\n";
}

}  // namespace

int main(int argc, char** argv) {
  std::string config_path, atlas_cache = "brainshift-atlas", summarise_path;
  std::vector<std::string> cases, subjects, modes{"labels+image", "labels", "image"};
  CLI::App app("brainshift hospital-variation benchmark: TRE per case and input mode, JSON records on stdout");
  app.add_option("--config", config_path);
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--cases", cases, "case names (default: all)")->delimiter(',');
  app.add_option("--subjects", subjects, "subject names (default: all)")->delimiter(',');
  app.add_option("--modes", modes, "labels+image, labels, image")->delimiter(',');
  app.add_option("--summarise", summarise_path, "records (NDJSON) to turn into the suite's document");
  std::string write_dir;
  app.add_option("--write-cases", write_dir, "write each case's images, labels, truth and landmarks under this directory");
  bool generate_only = false;
  app.add_flag("--generate-only", generate_only, "make (and write) the cases, register nothing");
  std::vector<double> snr_sweep;
  app.add_option("--snr", snr_sweep,
                 "run each selected case once per signal-to-noise ratio given (the scanner's SNR replaced; the "
                 "case named CASE_snrX): how the result falls off with the noise")
      ->delimiter(',')
      ->check(CLI::PositiveNumber);
  std::uint64_t reseed = 0;
  app.add_option("--reseed", reseed,
                 "draw every selected case and subject again from other seeds (K > 0; cases named CASE_reseedK): "
                 "a family of cases the engine was never tuned on");
  double cyst_fraction = 0;
  app.add_option("--cystic-tumours", cyst_fraction,
                 "the subjects' tumours get a fluid core of this fraction of their radius (0-0.9; cases named "
                 "CASE_cystF): a cystic tumour, fluid in the preop where its labels say tumour")
      ->check(CLI::Range(0.0, 0.9));
  bool contrast_enhanced = false;
  app.add_flag("--contrast-enhanced", contrast_enhanced,
               "every T1 case imaged contrast-enhanced (gadolinium: the dura and the resection margin enhance; "
               "cases named CASE_gd): the bright shell round the brain an intensity outline leaks into");
  bool flair = false;
  app.add_flag("--flair", flair,
               "every T1 case imaged FLAIR-like (the fluid dark, grey matter brighter than white; cases named "
               "CASE_flair): a contrast the engine was not made on");
  double slice_mm = 0;
  app.add_option("--slice-mm", slice_mm,
                 "every case's slices this thick (the scanner's through-plane spacing replaced, its slice profile "
                 "kept; cases named CASE_sliceXmm): the 2D multi-slice acquisitions some sites use intraop")
      ->check(CLI::Range(0.5, 8.0));
  double bias_amplitude = -1;
  app.add_option("--bias", bias_amplitude,
                 "every case's coil bias this strong (the scanner's amplitude replaced; cases named CASE_biasX): "
                 "a surface coil close to the craniotomy, a 3 T head's B1 shading")
      ->check(CLI::Range(0.0, 0.8));
  int coil_loops = 0;
  app.add_option("--coil-array", coil_loops,
                 "every case received by an array of this many surface loops round the head instead of the "
                 "polynomial bias (cases named CASE_coilsN): bright near the coils, darker in the middle, a shading "
                 "the engine's polynomial bias model does not share")
      ->check(CLI::Range(1, 64));
  double coil_shading = 1.0;
  app.add_option("--coil-shading", coil_shading, "with --coil-array: the array's shading raised to this power "
                                                 "(1: no intensity normalisation; default 1)")
      ->check(CLI::Range(0.0, 2.0));
  double turn_deg = 0;
  app.add_option("--turn-heads", turn_deg,
                 "every case's head turned in its clamp, which the scanner's RAS does not follow: a yaw about S-I "
                 "drawn from the case's seed between a third of this and this (either side), pitch and roll up to "
                 "15 degrees, a translation up to 20 mm, composed after the case's own rigid move (cases named "
                 "CASE_turnedD): a lateral or temporal approach")
      ->check(CLI::Range(0.0, 90.0));
  bool list_subjects = false;
  app.add_flag("--list-subjects", list_subjects, "print the selected cases' subjects, one a line");
  CLI11_PARSE(app, argc, argv);
  std::vector<HospitalCaseSpec> suite = reseeded(with_snr_sweep(selected(cases, subjects), snr_sweep), reseed);
  if (cyst_fraction > 0)
    for (auto& c : suite) {
      char suffix[32];
      std::snprintf(suffix, sizeof suffix, "_cyst%g", cyst_fraction);
      c.deformation.name += suffix;
    }
  if (contrast_enhanced)
    for (auto& c : suite)
      if (c.scanner.contrast == Contrast::t1) {
        c.scanner.contrast = Contrast::t1_contrast_enhanced;
        c.deformation.name += "_gd";
      }
  if (flair)
    for (auto& c : suite)
      if (c.scanner.contrast == Contrast::t1) {
        c.scanner.contrast = Contrast::flair_like;
        c.deformation.name += "_flair";
      }
  if (slice_mm > 0)
    for (auto& c : suite) {
      c.scanner.spacing_mm[2] = slice_mm;
      char suffix[32];
      std::snprintf(suffix, sizeof suffix, "_slice%gmm", slice_mm);
      c.deformation.name += suffix;
    }
  if (bias_amplitude >= 0)
    for (auto& c : suite) {
      c.scanner.bias_amplitude = bias_amplitude;
      char suffix[32];
      std::snprintf(suffix, sizeof suffix, "_bias%g", bias_amplitude);
      c.deformation.name += suffix;
    }
  if (coil_loops > 0)
    for (auto& c : suite) {
      c.scanner.coil_loops = coil_loops;
      c.scanner.coil_shading = coil_shading;
      char suffix[48];
      std::snprintf(suffix, sizeof suffix, "_coils%d", coil_loops);
      c.deformation.name += suffix;
      if (coil_shading != 1.0) c.deformation.name += "_shading" + std::to_string(coil_shading).substr(0, 4);
    }
  if (turn_deg > 0)
    for (auto& c : suite) {
      std::mt19937_64 rng(c.deformation.seed * 7919 + 17);
      std::uniform_real_distribution<double> unit(-1.0, 1.0);
      const double yaw = unit(rng);
      auto& rigid = c.deformation.rigid;
      rigid.rotation_deg += Eigen::Vector3d(15 * unit(rng), 15 * unit(rng),
                                            (yaw < 0 ? -1 : 1) * turn_deg * (1 + 2 * std::abs(yaw)) / 3);
      rigid.translation_mm += Eigen::Vector3d(20 * unit(rng), 20 * unit(rng), 20 * unit(rng));
      char suffix[32];
      std::snprintf(suffix, sizeof suffix, "_turned%g", turn_deg);
      c.deformation.name += suffix;
    }
  if (!summarise_path.empty()) return summarise(summarise_path, suite, modes);
  if (list_subjects) {
    std::set<std::string> seen;
    for (const auto& s : suite)
      if (seen.insert(s.subject).second) std::printf("%s\n", s.subject.c_str());
    return 0;
  }

  std::vector<evaluation::InputMode> run_modes;
  for (const auto& m : modes) run_modes.push_back(evaluation::mode_from_name(m));
  PetscSession petsc;
  if (!bench::drive_from_this_rank()) return 0;
  const PipelineParameters params = bench::parameters(config_path);
  const evaluation::AtlasInputs atlas = evaluation::load_atlas_inputs(atlas_cache);
  std::unique_ptr<EngineSession> session;
  std::unique_ptr<Subject> subject;
  bool warm = false;  // the current subject's warm-up succeeded
  std::string failed_subject;
  for (const auto& spec : suite) {
    if (failed_subject == spec.subject) continue;
    if (!subject || subject->name != spec.subject) {
      failed_subject = spec.subject;  // until it is made
      session.reset();
      try {
        subject = std::make_unique<Subject>(evaluation::make_named_subject(atlas, spec.subject, kReseedStride * reseed, cyst_fraction));
      } catch (const std::exception& e) {
        emit({{"record", "preop"}, {"subject", spec.subject}, {"status", "failed"}, {"note", std::string("subject: ") + e.what()}});
        subject.reset();
        continue;
      }
      emit({{"record", "preop"}, {"subject", spec.subject}, {"status", "started"}, {"subject_description", subject->description}});
      if (!write_dir.empty()) write_subject(write_dir, *subject);
      failed_subject.clear();
      warm = !generate_only && warm_up(session, params, *subject);
    }
    if (!generate_only && !warm) continue;  // summarise marks the case
    const HospitalCase c = make_hospital_case(*subject, spec);
    if (!write_dir.empty()) write_case(write_dir, spec, c);
    std::vector<evaluation::ModeRun> runs;
    if (!generate_only)
      for (auto m : run_modes) runs.push_back(evaluation::run_mode(*session, c, m));
    emit(evaluation::case_record(spec, c, runs));
    for (const auto& r : runs) {
      const std::string what = r.status != evaluation::ModeRun::Status::ran ? r.note
                               : std::to_string(r.result.nonrigid_mean_mm) + " mm" +
                                     (r.result.fallback ? " FALLBACK " + r.result.fallback_reason : "");
      std::fprintf(stderr, "%s [%s] %s: %s\n", spec.deformation.name.c_str(), spec.subject.c_str(),
                   evaluation::mode_name(r.mode), what.c_str());
    }
  }
  return 0;
}
