#pragma once
// The robustness suite's anatomy and runs (engine/phantom/robustness_case.h):
// which preop map a case registers against, the truth its intraop
// segmentation comes from, and one case registered with and without its
// intraop T1. Shared by the CI subset (test_robustness.cpp) and the benchmark.
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
};

// session must hold anatomy.preop. Both registrations use the same case.
// with_uncertainty: each result also gets its uncertainty map (after the
// timed stages), sampled at the landmarks (CaseResult::predicted_band_mm).
RobustnessRun run_robustness_case(EngineSession& session, const CaseAnatomy& anatomy, const RobustnessSpec& spec,
                                  bool with_uncertainty = false);

}  // namespace brainshift::evaluation
