#include "robustness_evaluation.h"

#include "atlas/default_atlas.h"
#include "core/label_colour.h"
#include "phantom/independent_labels.h"
#include "phantom/tumor_implant.h"

namespace brainshift::evaluation {

RobustnessInputs load_robustness_inputs(const std::string& atlas_cache, const std::string& templates_dir) {
  DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache, templates_dir);
  RobustnessInputs in;
  in.independent_labels = build_independent_labels(atlas.t1, templates_dir).labels;
  in.t1 = std::move(atlas.t1);
  in.atlas_labels = std::move(atlas.labels);
  return in;
}

CaseAnatomy case_anatomy(const RobustnessInputs& in, const RobustnessSpec& spec) {
  CaseAnatomy a;
  a.preop_key = spec.preop_is_truth ? "independent" : "atlas";
  a.preop.t1 = in.t1;
  a.truth_labels = in.independent_labels;
  a.preop.labels = spec.preop_is_truth ? in.independent_labels : in.atlas_labels;
  if (spec.phantom.preop_tumor) {
    const TumorImplantSpec& tumor = *spec.phantom.preop_tumor;
    implant_tumor(a.preop.t1, a.truth_labels, tumor);
    for (std::size_t v = 0; v < a.truth_labels.voxels.size(); ++v) {
      std::uint16_t& p = a.preop.labels.voxels[v];
      if (a.truth_labels.voxels[v] == tumor.label && (p == atlas_labels::brain || p == atlas_labels::corticospinal_tract))
        p = tumor.label;
    }
    a.preop_key += "+tumor" + std::to_string(tumor.seed);
  }
  return a;
}

RobustnessRun run_robustness_case(EngineSession& session, const CaseAnatomy& anatomy, const RobustnessSpec& spec,
                                  bool with_uncertainty) {
  PhantomSpec phantom = spec.phantom;
  phantom.preop_tumor.reset();  // already in anatomy.preop and the truth
  RobustnessSpec s = spec;
  s.phantom = phantom;
  const PhantomCase c = make_robustness_case(anatomy.preop.t1, anatomy.truth_labels, s);
  RobustnessRun run;
  const auto registered = [&](const IntraopInput& input) {
    ScanResult r = session.register_scan(input, nullptr);
    if (with_uncertainty) session.add_uncertainty(input, r, nullptr);
    return evaluate_result(spec.phantom.name, c, r);
  };
  run.with_image = registered({c.intraop_labels, c.intraop_t1});
  run.labels_only = registered({c.intraop_labels, std::nullopt});
  return run;
}

}  // namespace brainshift::evaluation
