#pragma once
// The robustness suite's anatomy and runs (engine/phantom/robustness_case.h):
// which preop map a case registers against, the truth its intraop
// segmentation comes from, and one case registered with and without its
// intraop T1. Shared by the CI subset (test_robustness.cpp) and the benchmark.
#include <optional>
#include <string>

#include "phantom/robustness_case.h"
#include "phantom_evaluation.h"

namespace brainshift::evaluation {

struct RobustnessInputs {
  ImageF t1;                      // Colin27 ch2
  LabelImage atlas_labels;        // the default atlas's map
  LabelImage independent_labels;  // phantom/independent_labels.h: another segmentation, with the horns
};

// Reads the atlas (cached in atlas_cache) and builds the independent map.
RobustnessInputs load_robustness_inputs(const std::string& atlas_cache,
                                        const std::string& templates_dir = "/usr/share/mricron/templates");

struct CaseAnatomy {
  std::string preop_key;   // cases with equal keys share one warm preop
  PreopInput preop;        // what the engine registers against
  LabelImage truth_labels; // what the intraop segmentation is made from (same grid as preop.t1)
};

// The truth is always the independent map; the preop is that map or the
// atlas's. A resection case implants its tumour into the T1 and the truth, and
// gives the atlas's map the same tumour voxels.
CaseAnatomy case_anatomy(const RobustnessInputs& in, const RobustnessSpec& spec);

struct RobustnessRun {
  CaseResult with_image, labels_only;
  // With image_only: the same case registered from its intraop image alone,
  // and the engine's segmentation against the truth carried by the true field
  // ({"brain_dice", "ventricles_dice"}; brain = the outline).
  std::optional<CaseResult> image_only;
  nlohmann::json segmentation;
};

// session must hold anatomy.preop. Every registration uses the same case.
// with_uncertainty: each result also gets its uncertainty map (after the
// timed stages), sampled at the landmarks (CaseResult::predicted_band_mm).
RobustnessRun run_robustness_case(EngineSession& session, const CaseAnatomy& anatomy, const RobustnessSpec& spec,
                                  bool with_uncertainty = false, bool image_only = false);

// Dice of a segmentation in the table's values (1 brain, 2 ventricles)
// against the truth carried onto the intraop grid by the true field.
nlohmann::json segmentation_dice(const LabelImage& segmentation, const LabelImage& truth_preop,
                                 const VectorImage3& true_pullback_mm, bool resected_tumor, std::uint16_t tumor_label);

}  // namespace brainshift::evaluation
