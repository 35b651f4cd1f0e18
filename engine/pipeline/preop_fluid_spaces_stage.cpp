#include "pipeline/preop_fluid_spaces_stage.h"

#include <algorithm>

#include "core/timer.h"
#include "image/resample.h"
#include "pipeline/segmentation_rounds.h"
#include "pipeline/working_grid.h"
#include "registration/affine_registration.h"
#include "registration/boundary_samples.h"
#include "segmentation/preop_fluid_spaces.h"

namespace brainshift {
namespace {

// The stage grid's spacing (auto_segmentation.passes.stage_spacing_mm, the
// mesh's surface facet): the spaces given back are at least 3 mm wide.
constexpr double kPlacementSpacingMm = 2.0;

}  // namespace

IntraopInput with_preop_fluid_spaces(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                     nlohmann::json& report) {
  const Stopwatch watch;
  const LabelTable& table = params.label_table;
  const auto cavities = table.cavity_labels();
  const std::uint16_t ventricle = cavities.empty() ? 0 : cavities.front();
  const auto& medians = preop_fluid_tissue_medians(warm, table);
  // The placement only needs to put a space of several mm on itself: the
  // labels on a 2 mm grid and a placement's affine (placement_affine). On
  // the three cases written to check it, it gave back the spaces the full
  // affine on the 1 mm labels did within 0.3 ml, mean TRE within 0.016 mm
  // (docs/PERFORMANCE.md 12.33), in about a quarter of the time.
  // The labels' pass keeps its own full affine.
  const Grid3 placement_grid = working_grid(input.labels.grid, kPlacementSpacingMm);
  const LabelImage placed_labels = placement_grid.dims == input.labels.grid.dims
                                       ? input.labels
                                       : downsample_labels(input.labels, placement_grid);
  const IntraopDistanceMaps maps = prepare_intraop_maps(placed_labels, table.brain_label(), ventricle);
  const AffineRegistrationResult affine = register_affine(warm.affine_samples, maps, placement_affine(params.affine));
  if (!affine.converged) {
    report = {{"applied", false}, {"why", "the labels' affine did not converge"}};
    IntraopInput out = input;
    out.read_seconds += watch.seconds();
    return out;
  }
  const segmentation::PreopFluidSpacesInput in{input.labels,       input.t1 ? &*input.t1 : nullptr,
                                               warm.preop.labels,  warm.preop.t1,
                                               affine.intraop_from_preop, table.brain_label(),
                                               ventricle,          medians[0],
                                               medians[1]};
  segmentation::PreopFluidSpaces spaces = segmentation::adopt_preop_fluid_spaces(in, {});
  report = std::move(spaces.report);
  // Part of preparing the input: counted in the scan's "read" and "total".
  IntraopInput out = input;
  out.read_seconds += watch.seconds();
  report["seconds"] = watch.seconds();
  if (spaces.added_ml > 0) out.labels = std::move(spaces.labels);
  return out;
}

}  // namespace brainshift
