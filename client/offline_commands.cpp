// `brainshift register` and `brainshift phantom`: the engine in this process.
#include "offline_commands.h"

#include <mpi.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <optional>

#include "atlas/default_atlas.h"
#include "config_file.h"
#include "exit_codes.h"
#include "core/errors.h"
#include "core/timer.h"
#include "fem/petsc_session.h"
#include "image/dicom_series.h"
#include "image/label_placement.h"
#include "image/nifti_io.h"
#include "image/nrrd_io.h"
#include "phantom/brain_shift_phantom.h"
#include "phantom/phantom_dicom.h"
#include "pipeline/engine_session.h"
#include "pipeline/scan_outputs.h"
#include "pipeline/scan_report.h"
#include "protocol/fields.h"

namespace brainshift::cli {
namespace fs = std::filesystem;
namespace {

fs::path default_atlas_cache() {
  if (const char* xdg = std::getenv("XDG_CACHE_HOME"); xdg && *xdg) return fs::path(xdg) / "brainshift" / "atlas";
  if (const char* home = std::getenv("HOME"); home && *home) return fs::path(home) / ".cache" / "brainshift" / "atlas";
  return fs::path("brainshift-atlas");
}

struct PreopPaths {
  std::string image, labels, atlas_cache;
  std::string dicom, series;  // the preop image as a DICOM series instead of image
};

// A scalar image given as a NIfTI file or as a DICOM series folder (one of
// them); a series' PatientID goes to patient_id (left as it is otherwise).
ImageF read_scalar_input(const std::string& nifti, const std::string& dicom, const std::string& series,
                         const std::string& option, std::size_t max_bytes, std::string* patient_id = nullptr) {
  if (!nifti.empty() && !dicom.empty()) throw InputError("give --" + option + "-image or --" + option + "-dicom, not both");
  if (!series.empty() && dicom.empty()) throw InputError("--" + option + "-series needs --" + option + "-dicom");
  if (!dicom.empty()) return read_dicom_series(dicom, series, max_bytes, patient_id);
  if (is_nrrd_path(nifti)) return read_nrrd_scalar(nifti, max_bytes);
  return read_scalar_image(nifti, max_bytes);
}

// A label map as NIfTI, NRRD or a Slicer segmentation (segment names mapped
// to the label table).
LabelImage read_label_input(const std::string& path, const LabelTable& table, std::size_t max_bytes) {
  if (is_slicer_segmentation_path(path)) return read_slicer_segmentation(path, table, max_bytes);
  if (is_nrrd_path(path)) return read_nrrd_labels(path, max_bytes);
  return read_label_image(path, max_bytes);
}

// Reads the preop pair, or the default atlas (in the table's values) when
// neither path is given.
PreopInput read_preop(const PreopPaths& paths, const LabelTable& table, std::string* patient_id = nullptr) {
  const bool has_image = !paths.image.empty() || !paths.dicom.empty();
  if (has_image != !paths.labels.empty())
    throw InputError("give both --preop-image (or --preop-dicom) and --preop-labels, or neither (default atlas)");
  if (!has_image) {
    const fs::path cache = paths.atlas_cache.empty() ? default_atlas_cache() : fs::path(paths.atlas_cache);
    DefaultAtlas atlas = load_or_build_default_atlas(cache);
    return PreopInput{std::move(atlas.t1), atlas_labels_for(atlas.labels, table)};
  }
  ImageF t1 = read_scalar_input(paths.image, paths.dicom, paths.series, "preop", static_cast<std::size_t>(-1), patient_id);
  LabelImage labels = labels_on_image_grid(read_label_input(paths.labels, table, static_cast<std::size_t>(-1)), t1.grid,
                                           paths.labels);
  return PreopInput{std::move(t1), std::move(labels)};
}

PipelineParameters read_parameters(const std::string& config_path) {
  return config_path.empty() ? config::pipeline_parameters_from_text(config::default_config_text(), "built-in brainshiftd.toml")
                             : config::pipeline_parameters_from_file(config_path);
}

void print_progress(const std::string& phase, const std::string& stage, double fraction, double seconds) {
  if (fraction >= 1.0)
    std::fprintf(stderr, "[%s] %-10s %8.3f s\n", phase.c_str(), stage.c_str(), seconds);
  else if (fraction <= 0.0)
    std::fprintf(stderr, "[%s] %-10s ...\n", phase.c_str(), stage.c_str());
}

struct RegisterOptions {
  PreopPaths preop;
  std::string intraop_labels, intraop_image, out, config;
  std::string intraop_dicom, intraop_series;
  std::string labels_use;  // empty: the configuration's given_labels
};

// Both series name their patient: they must name the same one (compared as
// the daemon compares preop.load's and scan.push's patient_id).
// An identifier that is not text (a character set the files do not
// declare) is compared as written: both came from DICOM files.
void check_same_patient(const std::string& preop_dicom_id, const std::string& intraop_dicom_id) {
  const auto as_compared = [](const std::string& id) -> std::optional<std::string> {
    if (id.find_first_not_of(' ') == std::string::npos) return std::nullopt;
    return protocol::detail::normalised_patient_id(id).value_or(id);
  };
  const auto preop = as_compared(preop_dicom_id);
  const auto intraop = as_compared(intraop_dicom_id);
  if (preop && intraop && *preop != *intraop)
    throw InputError("the intraop series is of patient \"" + *intraop + "\" and the preop series of patient \"" + *preop +
                     "\": a scan of another patient is not registered");
}

int run_register_rank0(const RegisterOptions& o) {
  const PipelineParameters params = read_parameters(o.config);
  // The intraop files are read first: a broken scan is refused in a moment
  // instead of after minutes of meshing the preop.
  Stopwatch read_clock;
  const bool has_image = !o.intraop_image.empty() || !o.intraop_dicom.empty();
  if (o.intraop_labels.empty() && !has_image)
    throw InputError("give --intraop-image (or --intraop-dicom), --intraop-labels, or both");
  ScanInput scan;
  std::string intraop_patient, preop_patient;  // DICOM PatientIDs, "" unknown
  if (!o.intraop_labels.empty())
    scan.labels = read_label_input(o.intraop_labels, params.label_table, params.max_image_bytes);
  if (has_image)
    scan.image = read_scalar_input(o.intraop_image, o.intraop_dicom, o.intraop_series, "intraop", params.max_image_bytes,
                                   &intraop_patient);
  if (scan.labels && scan.image) scan.labels = labels_on_image_grid(std::move(*scan.labels), scan.image->grid, o.intraop_labels);
  scan.read_seconds = read_clock.seconds();
  if (!o.labels_use.empty()) scan.labels_use = given_labels_use_from_string(o.labels_use);

  EngineSession session(MPI_COMM_WORLD, params);
  Stopwatch atlas_clock;
  PreopInput preop = read_preop(o.preop, params.label_table, &preop_patient);
  check_same_patient(preop_patient, intraop_patient);
  session.set_atlas_seconds(atlas_clock.seconds());
  print_progress("preop", "atlas", 1.0, atlas_clock.seconds());
  session.load_preop(std::move(preop), [](const std::string& s, double f, double t) { print_progress("preop", s, f, t); });
  std::fprintf(stderr, "[preop] mesh: %zu nodes, %zu tets\n", session.mesh().node_count(), session.mesh().tet_count());

  ScanResult result = session.register_scan(scan, [](const std::string& s, double f, double t) { print_progress("intraop", s, f, t); });
  // After the answer, as the daemon does: not part of "total".
  // The prepared input: the segmentation the engine made (of an image alone,
  // or given labels refined by their image), or the labels as given.
  const IntraopInput prepared{result.labels_used(scan.labels), scan.image};
  session.add_uncertainty(prepared, result, [](const std::string& s, double f, double t) { print_progress("intraop", s, f, t); });
  DeferredOutputOptions outputs;
  outputs.label_table = &session.parameters().label_table;
  // register has no scan id: the output folder names the report.
  const fs::path out_dir = fs::path(o.out).filename().empty() ? fs::path(o.out).parent_path() : fs::path(o.out);
  outputs.scan_id = out_dir.filename().string();
  write_scan_outputs(result, scan.image ? &*scan.image : nullptr, o.out, outputs);
  std::fprintf(stderr, "[intraop] total      %8.3f s\n", result.timings["intraop"]["total"].get<double>());
  std::cout << "wrote " << o.out << '\n';
  if (const std::string caution = result_caution(result.metrics); !caution.empty())
    std::fprintf(stderr, "CAUTION: %s\n", caution.c_str());
  if (result.kind == ResultKind::affine_only_fallback) {
    std::fprintf(stderr, "WARNING: non-rigid registration refused (%s); the outputs hold the AFFINE-ONLY result\n",
                 result.fallback_reason.c_str());
    return kExitFallback;
  }
  return kExitOk;
}

// Every rank parses the same command line; ranks > 0 only serve the FEM.
int run_register(const RegisterOptions& o) {
  PetscSession petsc;
  int rank = 0;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  if (rank != 0) {
    run_worker_loop(MPI_COMM_WORLD);
    return kExitOk;
  }
  try {
    return run_register_rank0(o);
  } catch (const InputError& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: registration failed: %s\n", e.what());
  }
  // EngineSession's destructor has released the workers by now.
  return kExitError;
}

// The files a phantom case is made of; landmarks.json pairs intraop points
// with their true preop points (world RAS mm).
void write_phantom_case(const PhantomCase& c, const fs::path& dir) {
  fs::create_directories(dir);
  write_scalar_image(dir / "intraop_t1.nii.gz", c.intraop_t1);
  write_label_image(dir / "intraop_labels.nii.gz", c.intraop_labels);
  write_displacement_field(dir / "true_field.nii.gz", c.true_pullback_mm);
  nlohmann::json landmarks = nlohmann::json::array();
  for (const auto& [x, p] : c.landmarks_intraop_preop_mm)
    landmarks.push_back({{"intraop_mm", {x.x(), x.y(), x.z()}}, {"preop_mm", {p.x(), p.y(), p.z()}}});
  std::ofstream(dir / "landmarks.json") << landmarks.dump(1) << '\n';
  std::ofstream(dir / "description.json") << c.description.dump(2) << '\n';
}

struct PhantomOptions {
  PreopPaths preop;
  std::string preset, out;
  unsigned seed = 1;
  bool list = false;
  bool dicom = false;  // also the intraop T1 as a DICOM series (intraop_dicom/)
};

int run_phantom(const PhantomOptions& o) {
  try {
    const auto suite = standard_phantom_suite();
    if (o.list) {
      for (const auto& spec : suite) std::cout << spec.name << '\n';
      return kExitOk;
    }
    const PhantomSpec* chosen = nullptr;
    for (const auto& spec : suite)
      if (spec.name == o.preset) chosen = &spec;
    if (!chosen) throw InputError("unknown phantom preset \"" + o.preset + "\" (see --list)");
    PhantomSpec spec = *chosen;
    spec.seed = o.seed;
    // The phantom's presets name the atlas's own values (the shipped table's).
    PreopInput preop = read_preop(o.preop, config::default_label_table());
    if (spec.preop_tumor) {
      // The case resects a tumor the preop must have: register against the
      // preop written next to it.
      implant_tumor(preop.t1, preop.labels, *spec.preop_tumor);
      fs::create_directories(o.out);
      write_scalar_image(fs::path(o.out) / "preop_t1.nii.gz", preop.t1);
      write_label_image(fs::path(o.out) / "preop_labels.nii.gz", preop.labels);
      std::cout << "this case has a tumor in its preop: register with --preop-image " << o.out
                << "/preop_t1.nii.gz --preop-labels " << o.out << "/preop_labels.nii.gz\n";
    }
    const PhantomCase c = make_phantom(preop.t1, preop.labels, spec);
    write_phantom_case(c, o.out);
    if (o.dicom) write_dicom_series(c.intraop_t1, fs::path(o.out) / "intraop_dicom", dicom_series_spec_of(c.intraop_t1));
    std::cout << "wrote " << o.out << '\n';
    return kExitOk;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return kExitError;
  }
}

void add_preop_options(CLI::App* cmd, PreopPaths& p) {
  cmd->add_option("--preop-image", p.image, "preop T1 (NIfTI); default: the built-in Colin27 atlas");
  cmd->add_option("--preop-labels", p.labels, "preop label map on the T1's grid or a part of it (NIfTI, NRRD or Slicer .seg.nrrd)");
  cmd->add_option("--preop-dicom", p.dicom, "preop T1 as a DICOM series folder, instead of --preop-image");
  cmd->add_option("--preop-series", p.series, "SeriesInstanceUID in --preop-dicom when it holds several");
  cmd->add_option("--atlas-cache", p.atlas_cache, "where the default atlas is cached (default ~/.cache/brainshift/atlas)");
}

}  // namespace

void add_offline_commands(CLI::App& app, int* exit_code) {
  auto reg = std::make_shared<RegisterOptions>();
  CLI::App* r = app.add_subcommand("register", "one-shot registration in this process (no daemon)");
  add_preop_options(r, reg->preop);
  r->add_option("--intraop-labels", reg->intraop_labels,
                "intraop label map (1 brain, 2 lateral ventricles): NIfTI, NRRD or Slicer .seg.nrrd; without it "
                "the image is segmented (intraop_labels.nii.gz and segmentation_confidence.nii.gz are written)");
  r->add_option("--intraop-image", reg->intraop_image, "intraop MR image (the labels on its grid, or on a part of it, when both are given)");
  r->add_option("--intraop-dicom", reg->intraop_dicom, "intraop image as a DICOM series folder, instead of --intraop-image");
  r->add_option("--intraop-series", reg->intraop_series, "SeriesInstanceUID in --intraop-dicom when it holds several");
  r->add_option("--labels-use", reg->labels_use,
                "labels with an image: refine (the image is classified under them; an algorithm's labels) or exact "
                "(as given; corrected by hand); default: the configuration's given_labels")
      ->check(CLI::IsMember({"refine", "exact"}));
  r->add_option("--out", reg->out, "output folder (written atomically)")->required();
  r->add_option("--config", reg->config, "configuration TOML (default: the built-in config/brainshiftd.toml)");
  r->callback([reg, exit_code] { *exit_code = run_register(*reg); });

  auto ph = std::make_shared<PhantomOptions>();
  CLI::App* p = app.add_subcommand("phantom", "make a synthetic brain-shift case with a known field");
  add_preop_options(p, ph->preop);
  p->add_option("--preset", ph->preset, "deformation preset (see --list)");
  p->add_option("--seed", ph->seed, "random seed (noise, landmarks)");
  p->add_option("--out", ph->out, "output folder");
  p->add_flag("--list", ph->list, "list the presets and exit");
  p->add_flag("--dicom", ph->dicom, "also write the intraop T1 as a DICOM series (OUT/intraop_dicom), as a scanner would");
  p->callback([ph, exit_code] {
    if (!ph->list && (ph->preset.empty() || ph->out.empty())) {
      std::fprintf(stderr, "error: phantom needs --preset and --out (or --list)\n");
      *exit_code = 2;
      return;
    }
    *exit_code = run_phantom(*ph);
  });
}

}  // namespace brainshift::cli
