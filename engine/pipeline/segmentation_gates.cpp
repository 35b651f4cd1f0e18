#include "pipeline/segmentation_gates.h"

#include <cmath>

#include "core/errors.h"
#include "image/image_stats.h"
#include "segmentation/tissue_prior.h"

namespace brainshift {
namespace {

// The inner band one voxel inside the outline's surface.
Mask inner_surface_band(const Mask& outline) {
  const double h = outline.grid.spacing_mm().minCoeff();
  return boundary_voxels(erode(outline, 1.01 * h));
}

}  // namespace

CarriedPreopVolumes carried_preop_volumes(const LabelImage& carried_preop, const LabelTable& table,
                                          double placement_volume_scale) {
  if (!(placement_volume_scale > 0) || !std::isfinite(placement_volume_scale))
    throw ComputeError("the head's placement is degenerate (volume scale " + std::to_string(placement_volume_scale) +
                       ")");
  CarriedPreopVolumes c;
  c.brain_ml = volume_ml(outline_mask(carried_preop)) / placement_volume_scale;
  for (auto v : table.resectable_labels())
    c.resectable_ml += volume_ml(mask_of_labels(carried_preop, {v})) / placement_volume_scale;
  c.ventricles_ml = volume_ml(mask_of_labels(carried_preop, table.cavity_labels())) / placement_volume_scale;
  return c;
}

SegmentationGates check_segmentation(const LabelImage& segmentation, const ImageF& confidence,
                                     const CarriedPreopVolumes& preop, const LabelTable& table,
                                     const AutoSegmentationParameters& params, double open_fluid_ml) {
  SegmentationGates g;
  const Mask outline = outline_mask(segmentation);
  const double resectable_ml = preop.resectable_ml;
  const double seg_ml = volume_ml(outline), preop_ml = preop.brain_ml;
  const double change = preop_ml > 0 ? seg_ml / preop_ml - 1 : -1;
  // Smaller by what may be resected, and by the fluid found in the gap a
  // sinking left (fluid by its intensity: a lost lobe is tissue).
  const double lowest =
      -params.max_brain_volume_change -
      (preop_ml > 0 ? (resectable_ml + open_fluid_ml + preop.lower_allowance_ml) / preop_ml : 0);
  g.metrics["brain_volume"] = {{"segmented_ml", seg_ml}, {"preop_ml", preop_ml}, {"change", change},
                               {"open_fluid_ml", open_fluid_ml},
                               {"allowed", {lowest, params.max_brain_volume_change}}};
  if (preop.lower_allowance_ml > 0) g.metrics["brain_volume"]["lower_allowance_ml"] = preop.lower_allowance_ml;
  if (change < lowest || change > params.max_brain_volume_change) {
    g.geometry_refused = true;
    g.failure = "automatic segmentation: the brain's volume differs from the preop's by " +
                std::to_string(100 * change) + " % (allowed " + std::to_string(100 * lowest) + " to +" +
                std::to_string(100 * params.max_brain_volume_change) + " %)";
  }

  const auto vent = table.cavity_labels();
  const double seg_vent = volume_ml(mask_of_labels(segmentation, vent));
  const double preop_vent = preop.ventricles_ml;
  const double fraction = preop_vent > 0 ? seg_vent / preop_vent : 1.0;
  g.metrics["ventricles"] = {{"segmented_ml", seg_vent}, {"preop_ml", preop_vent}, {"fraction", fraction},
                             {"min_fraction", params.min_ventricle_fraction}};
  if (g.failure.empty() && preop_vent > 0 && fraction < params.min_ventricle_fraction)
    g.failure = "automatic segmentation: no ventricles found (" + std::to_string(seg_vent) + " ml against " +
                std::to_string(preop_vent) + " ml preop)";

  const VoxelBox box = grow_box(bounding_box_voxels(outline), outline.grid, 3.0);
  std::size_t band_voxels = 0, uncertain = 0;
  if (!box.empty) {
    const Mask band = inner_surface_band(crop_to_box(outline, box));
    for (int k = 0; k < band.grid.dims[2]; ++k)
      for (int j = 0; j < band.grid.dims[1]; ++j)
        for (int i = 0; i < band.grid.dims[0]; ++i) {
          if (!band.at(i, j, k)) continue;
          ++band_voxels;
          uncertain += confidence.at(i + box.lo[0], j + box.lo[1], k + box.lo[2]) < params.min_surface_confidence;
        }
  }
  const double uncertain_fraction = band_voxels ? static_cast<double>(uncertain) / static_cast<double>(band_voxels) : 1.0;
  g.metrics["outer_surface"] = {{"uncertain_fraction", uncertain_fraction},
                                {"min_confidence", params.min_surface_confidence},
                                {"max_uncertain_fraction", params.max_uncertain_surface_fraction}};
  if (g.failure.empty() && uncertain_fraction > params.max_uncertain_surface_fraction)
    g.failure = "automatic segmentation: the outer brain surface is uncertain over " +
                std::to_string(100 * uncertain_fraction) + " % of its area (limit " +
                std::to_string(100 * params.max_uncertain_surface_fraction) + " %)";
  g.metrics["passed"] = g.failure.empty();
  return g;
}

SegmentationGates check_segmentation(const LabelImage& segmentation, const ImageF& confidence,
                                     const LabelImage& carried_preop, const LabelTable& table,
                                     const AutoSegmentationParameters& params, double open_fluid_ml) {
  return check_segmentation(segmentation, confidence, carried_preop_volumes(carried_preop, table), table, params,
                            open_fluid_ml);
}

}  // namespace brainshift
