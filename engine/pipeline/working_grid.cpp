#include "pipeline/working_grid.h"

#include <cmath>

#include "core/timer.h"
#include "field/vector_sampling.h"
#include "field/warp.h"
#include "image/resample.h"
#include "protocol/stage_names.h"

namespace brainshift {

void carry_to_grid(const WarmState& warm, ScanResult& result, const Grid3& image_grid) {
  result.pullback_field_mm = resample_vector_linear(result.pullback_field_mm, image_grid);
  // Each warp splits its slices over both cores (field/warp.h).
  result.warped_labels = warp_labels_nearest(warm.preop.labels, result.pullback_field_mm);
  if (!result.warped_t1.voxels.empty()) result.warped_t1 = warp_image_linear(warm.preop.t1, result.pullback_field_mm);
  if (!result.warped_t1_affine_only.voxels.empty())
    result.warped_t1_affine_only =
        resample_linear(warm.preop.t1, image_grid, result.intraop_from_preop.inverse());
  if (result.intraop_labels) result.intraop_labels = resample_nearest(*result.intraop_labels, image_grid);
  if (result.segmentation_confidence)
    result.segmentation_confidence = resample_linear(*result.segmentation_confidence, image_grid);
  if (!result.uncertainty_mm.voxels.empty()) result.uncertainty_mm = resample_linear(result.uncertainty_mm, image_grid);
}

void report_working_grid(ScanResult& result, const Grid3& work, const Grid3& image_grid, double seconds,
                         const std::string& key) {
  const auto triple = [](const auto& v) { return nlohmann::json::array({v[0], v[1], v[2]}); };
  result.metrics[key] = {{"dims", triple(work.dims)}, {"spacing_mm", triple(work.spacing_mm())},
                         {"image_dims", triple(image_grid.dims)},
                         {"image_spacing_mm", triple(image_grid.spacing_mm())}};
  auto& t = result.timings["intraop"];
  t[key] = seconds;
  const std::string total(protocol::stages::kTotal);
  t[total] = t.value(total, 0.0) + seconds;
}

ScanResult run_intraop_on_working_grid(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                       const ProgressFn& progress, const std::string& forced_fallback,
                                       const PassOptions& pass) {
  const Grid3& grid = input.labels.grid;
  const Grid3 work = working_grid(grid, params.auto_segmentation.working_spacing_mm);
  if (work.dims == grid.dims) return run_intraop(warm, input, params, progress, false, forced_fallback, pass);
  validate_intraop_input(input, params.label_table);  // said of the labels as given
  Stopwatch watch;
  IntraopInput coarser{downsample_labels(input.labels, work), std::nullopt, input.read_seconds, input.open_fluid_ml};
  if (input.t1) coarser.t1 = downsample_linear(*input.t1, work);
  double own_seconds = watch.lap();
  ScanResult result = run_intraop(warm, coarser, params, progress, false, forced_fallback, pass);
  watch.lap();
  carry_to_grid(warm, result, grid);
  own_seconds += watch.lap();
  report_working_grid(result, work, grid, own_seconds);
  return result;
}

}  // namespace brainshift
