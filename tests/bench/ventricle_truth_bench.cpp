// Is the robustness suite's ventricle truth what its intraop image shows?
// For each case: the truth's lateral ventricles carried onto the intraop grid
// by the true field (as the suite scores a segmentation), and the best any
// segmentation of that image can do against them:
//   - "ideal": the image's fluid in the truth's ventricles dilated by
//     search_mm, cut at the partial-volume midpoint between the ventricles'
//     core (eroded truth) and the tissue 2-5 mm around them (both medians);
//   - "oracle": the same region cut at the threshold that maximises Dice
//     (an upper bound no classifier can beat with intensity alone).
// And on the preop grid (the noise-free 1 mm Colin27 T1 the truth was grown
// in): the truth against the same midpoint cut, i.e. how far the truth's own
// intensity limit (IndependentLabelParameters::csf_max) lies from the wall.
// JSON on stdout.
//   brainshift_ventricle_truth_bench [--atlas-cache DIR] [--cases a,b] [--search-mm MM] [--wall-at-csf-max]
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <set>

#include "atlas/default_atlas.h"
#include "field/warp.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "phantom/independent_labels.h"
#include "robustness_evaluation.h"

using namespace brainshift;

namespace {

double median_in(const ImageF& image, const Mask& m) {
  std::vector<float> x;
  for (std::size_t v = 0; v < m.voxels.size(); ++v)
    if (m.voxels[v]) x.push_back(image.voxels[v]);
  if (x.empty()) return 0;
  std::nth_element(x.begin(), x.begin() + static_cast<std::ptrdiff_t>(x.size() / 2), x.end());
  return x[x.size() / 2];
}

double dice(const Mask& a, const Mask& b) {
  std::size_t both = 0, na = 0, nb = 0;
  for (std::size_t v = 0; v < a.voxels.size(); ++v) {
    both += a.voxels[v] && b.voxels[v];
    na += a.voxels[v] != 0;
    nb += b.voxels[v] != 0;
  }
  return na + nb ? 2.0 * static_cast<double>(both) / static_cast<double>(na + nb) : 1.0;
}

// Voxels of `region` darker than t (T1: fluid is dark).
Mask below(const ImageF& image, const Mask& region, double t) {
  Mask m(region.grid, 0);
  for (std::size_t v = 0; v < m.voxels.size(); ++v) m.voxels[v] = region.voxels[v] && image.voxels[v] < t;
  return m;
}

nlohmann::json ceiling(const ImageF& image, const Mask& truth, const Mask& brain, double search_mm) {
  const Mask core = erode(truth, 1.0);
  const Mask near = dilate(truth, 2.0), far = dilate(truth, 5.0);
  Mask shell(truth.grid, 0), region(truth.grid, 0);
  const Mask search = dilate(truth, search_mm);
  for (std::size_t v = 0; v < shell.voxels.size(); ++v) {
    shell.voxels[v] = far.voxels[v] && !near.voxels[v] && brain.voxels[v];
    region.voxels[v] = search.voxels[v] && brain.voxels[v];
  }
  const double fluid = median_in(image, count_nonzero(core) ? core : truth), tissue = median_in(image, shell);
  const double mid = 0.5 * (fluid + tissue);
  const Mask ideal = below(image, region, mid);
  double best = 0, best_t = mid;
  for (int s = 0; s <= 100; ++s) {
    const double t = fluid + (tissue - fluid) * s / 100.0;
    const double d = dice(below(image, region, t), truth);
    if (d > best) best = d, best_t = t;
  }
  return {{"truth_ml", volume_ml(truth)},       {"fluid_median", fluid},
          {"tissue_median", tissue},            {"midpoint", mid},
          {"ideal_ml", volume_ml(ideal)},       {"ideal_dice", dice(ideal, truth)},
          {"oracle_threshold", best_t},         {"oracle_dice", best}};
}

}  // namespace

int main(int argc, char** argv) {
  std::string atlas_cache = "brainshift-atlas";
  std::vector<std::string> only;
  double search_mm = 3;
  CLI::App app("brainshift ventricle truth check: the best Dice the robustness suite's images allow");
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--cases", only, "case names (default: all)")->delimiter(',');
  app.add_option("--search-mm", search_mm, "how far around the truth's ventricles fluid is looked for");
  bool wall_at_csf_max = false;
  app.add_flag("--wall-at-csf-max", wall_at_csf_max, "the truth as the suite made it before its wall was placed at half fluid");
  CLI11_PARSE(app, argc, argv);

  evaluation::RobustnessInputs inputs = evaluation::load_robustness_inputs(atlas_cache);
  IndependentLabelParameters truth_params;
  truth_params.wall_at_half_fluid = !wall_at_csf_max;
  const IndependentLabels independent =
      build_independent_labels(inputs.t1, "/usr/share/mricron/templates", truth_params);
  inputs.independent_labels = independent.labels;
  const Mask preop_truth = mask_of_labels(inputs.independent_labels, {atlas_labels::ventricles});
  const Mask preop_brain = mask_of_labels(inputs.independent_labels, {atlas_labels::brain, atlas_labels::ventricles, atlas_labels::corticospinal_tract});
  nlohmann::json out;
  out["preop_noise_free"] = ceiling(inputs.t1, preop_truth, preop_brain, search_mm);
  out["truth_wall_t1"] = independent.wall_t1;
  out["truth_fluid_t1"] = independent.fluid_t1;
  out["truth_tissue_t1"] = independent.tissue_t1;
  out["truth_ventricle_components"] = independent.ventricle_components;
  // And the atlas's own ventricles (the preop map of half the cases) against the truth's.
  out["atlas_vs_truth_ventricle_dice"] =
      dice(mask_of_labels(inputs.atlas_labels, {atlas_labels::ventricles}), preop_truth);
  out["cases"] = nlohmann::json::array();
  std::vector<RobustnessSpec> suite = robustness_suite_cases(only);
  for (const auto& spec : suite) {
    const evaluation::CaseAnatomy anatomy = evaluation::case_anatomy(inputs, spec);
    RobustnessSpec s = spec;
    s.phantom.preop_tumor.reset();
    const PhantomCase c = make_robustness_case(anatomy.preop.t1, anatomy.truth_labels, s);
    const LabelImage truth = warp_labels_nearest(anatomy.truth_labels, c.true_pullback_mm);
    const Mask vent = mask_of_labels(truth, {atlas_labels::ventricles});
    Mask brain(truth.grid, 0);
    for (std::size_t v = 0; v < brain.voxels.size(); ++v) brain.voxels[v] = truth.voxels[v] != 0;
    nlohmann::json j = ceiling(c.intraop_t1, vent, brain, search_mm);
    j["case"] = spec.phantom.name;
    out["cases"].push_back(j);
    std::fprintf(stderr, "%s %s\n", spec.phantom.name.c_str(), j.dump().c_str());
  }
  std::printf("%s\n", out.dump(2).c_str());
  return 0;
}
