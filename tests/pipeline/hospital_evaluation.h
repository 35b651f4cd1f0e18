#pragma once
// The hospital-variation suite's runs (engine/phantom/hospital_suite.h): the
// subjects made from the default atlas, one case registered in each input
// mode, and the records the benchmark prints and pools.
#include <string>
#include <vector>

#include "phantom/hospital_suite.h"
#include "phantom_evaluation.h"

namespace brainshift::evaluation {

struct AtlasInputs {
  ImageF t1;
  LabelImage labels;
};
AtlasInputs load_atlas_inputs(const std::string& atlas_cache,
                              const std::string& templates_dir = "/usr/share/mricron/templates");

// The subject of hospital_subjects() with this name (InputError if none).
// seed_offset > 0: the subject's random reshaping (and its tumour's shape)
// drawn again from other seeds: another head of the same kind.
// cyst_radius_fraction > 0: the subject's tumour, if it has one, is cystic
// (TumorImplantSpec::cyst_radius_fraction).
Subject make_named_subject(const AtlasInputs& atlas, const std::string& name, std::uint64_t seed_offset = 0,
                           double cyst_radius_fraction = 0);

// What the engine is given: segmentation + intraop T1, segmentation alone,
// or the image alone (only where the engine accepts it).
enum class InputMode { labels_and_image, labels_only, image_only };
const char* mode_name(InputMode m);
InputMode mode_from_name(const std::string& name);  // InputError on an unknown name

struct ModeRun {
  InputMode mode = InputMode::labels_and_image;
  enum class Status { ran, skipped, error } status = Status::ran;
  std::string note;   // why skipped, or the error
  CaseResult result;  // when ran
  nlohmann::json segmentation;  // image only: Dice of the automatic segmentation vs the true labels
  nlohmann::json affine_stretch;  // the plausibility gate's value, limit and brain extents in view
  nlohmann::json warped_beyond_truth;  // preop tissue the warped labels draw outside the true brain
  nlohmann::json label_image_check;    // labels with their image: the check's figures (metrics.label_image_check)
  // labels with their image: refined or disregarded, what the refinement
  // changed (metrics.given_labels.changes) and the result's caution
  nlohmann::json given_labels;
  std::string caution;  // the result's (metrics.caution), any mode
};

// The preop tissue the warped labels draw outside the true intraop brain:
// ml more than 3 and 6 mm outside it, and the farthest (mm). A second image
// of the preop brain in the gap a sinking left shows here
// (field/tissue_guard.h); the outline's own partial volume stays within 3 mm.
nlohmann::json warped_beyond_truth(const LabelImage& warped, const LabelImage& truth);

// Brain (outline) and ventricle Dice of a segmentation against the truth.
nlohmann::json segmentation_agreement(const LabelImage& segmented, const LabelImage& truth,
                                      const std::vector<std::uint16_t>& ventricle_labels);

// Registers the case in one mode on the warm session. An image-only run the
// engine refuses with InputError is "skipped" with the reason (an image the
// automatic segmentation cannot use); other errors are recorded, not thrown.
ModeRun run_mode(EngineSession& session, const HospitalCase& c, InputMode mode);

// One case's record: the case's brief description and each mode's TRE,
// kind, fallback reason and time (with the landmark errors, for pooling).
nlohmann::json case_record(const HospitalCaseSpec& spec, const HospitalCase& c, const std::vector<ModeRun>& runs);
// A case that never ran (its subject's warm-up did not finish, ...).
nlohmann::json unfinished_case_record(const HospitalCaseSpec& spec, const std::string& why);

// The suite's document from the records (case records, preop records): per
// mode asked for (and any other mode found in the records) the non-rigid
// fraction (an unfinished case or an error counts against it, a skipped run
// is left out), mean TRE over cases, pooled p95, worst landmark; the
// landmark errors dropped from the cases.
nlohmann::json summarise_records(const std::vector<nlohmann::json>& records, const std::vector<std::string>& modes);

}  // namespace brainshift::evaluation
