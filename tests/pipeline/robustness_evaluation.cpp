#include "robustness_evaluation.h"

#include "atlas/default_atlas.h"
#include "core/errors.h"
#include "core/label_colour.h"
#include "field/warp.h"
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
                                  bool with_uncertainty, bool image_only) {
  PhantomSpec phantom = spec.phantom;
  phantom.preop_tumor.reset();  // already in anatomy.preop and the truth
  RobustnessSpec s = spec;
  s.phantom = phantom;
  const PhantomCase c = make_robustness_case(anatomy.preop.t1, anatomy.truth_labels, s);
  RobustnessRun run;
  const auto registered = [&](const IntraopInput& input) {
    // As the daemon registers a scan: given labels with an image are checked
    // against it (the labels-vs-image check), and the total includes that.
    ScanResult r = session.register_scan(ScanInput{input.labels, input.t1, input.read_seconds, std::nullopt}, nullptr);
    if (with_uncertainty) session.add_uncertainty(input, r, nullptr);
    return evaluate_result(spec.phantom.name, c, r);
  };
  run.with_image = registered({c.intraop_labels, c.intraop_t1});
  run.labels_only = registered({c.intraop_labels, std::nullopt});
  if (image_only) {
    ScanInput scan;
    scan.image = c.intraop_t1;
    try {
      ScanResult r = session.register_scan(scan, nullptr);
      // The map as the daemon makes it for an image-only scan: from the
      // automatic segmentation and the image.
      if (with_uncertainty) session.add_uncertainty(IntraopInput{*r.intraop_labels, c.intraop_t1}, r, nullptr);
      run.image_only = evaluate_result(spec.phantom.name, c, r);
      run.segmentation = segmentation_dice(*r.intraop_labels, anatomy.truth_labels, c.true_pullback_mm,
                                           spec.phantom.resection.enabled, spec.phantom.resection.tumor_label);
      run.segmentation["metrics"] = r.metrics["segmentation"];
    } catch (const InputError& e) {
      run.segmentation = {{"refused", e.what()}};
    }
  }
  return run;
}

nlohmann::json segmentation_dice(const LabelImage& segmentation, const LabelImage& truth_preop,
                                 const VectorImage3& true_pullback_mm, bool resected_tumor, std::uint16_t tumor_label) {
  const LabelImage truth = warp_labels_nearest(truth_preop, true_pullback_mm);
  std::size_t both_b = 0, seg_b = 0, tru_b = 0, both_v = 0, seg_v = 0, tru_v = 0;
  for (std::size_t v = 0; v < truth.voxels.size(); ++v) {
    const std::uint16_t t = truth.voxels[v], s = segmentation.voxels[v];
    const bool tb = t != 0 && !(resected_tumor && t == tumor_label), sb = s != 0;
    const bool tv = t == atlas_labels::ventricles, sv = s == atlas_labels::ventricles;
    both_b += tb && sb;
    seg_b += sb;
    tru_b += tb;
    both_v += tv && sv;
    seg_v += sv;
    tru_v += tv;
  }
  const auto dice = [](std::size_t both, std::size_t a, std::size_t b) {
    return a + b ? 2.0 * static_cast<double>(both) / static_cast<double>(a + b) : 1.0;
  };
  const double voxel_ml = truth.grid.spacing_mm().prod() / 1000.0;
  return {{"brain_dice", dice(both_b, seg_b, tru_b)},
          {"ventricles_dice", dice(both_v, seg_v, tru_v)},
          {"brain_ml",
           {{"segmented", voxel_ml * static_cast<double>(seg_b)}, {"truth", voxel_ml * static_cast<double>(tru_b)}}}};
}

}  // namespace brainshift::evaluation
