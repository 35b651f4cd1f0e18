#pragma once
// The gates of the automatic segmentation (docs/DESIGN.md "Automatic intraop
// segmentation"): a segmentation whose brain volume is far from the preop's,
// that finds no ventricles, or whose outer surface is uncertain over a large
// area is not trusted. The preop they compare with is the preop carried onto
// the intraop grid by the head's placement.
#include <nlohmann/json.hpp>
#include <string>

#include "pipeline/pipeline_parameters.h"

namespace brainshift {

// The gates of the automatic path on one segmentation: metrics (values and
// limits) and the first reason not to trust it ("" when none). open_fluid_ml:
// the fluid the segmentation found where sunken cortex was
// (IntraopSegmentation::open_fluid_ml), by which the brain is smaller.
struct SegmentationGates {
  nlohmann::json metrics;
  std::string failure;
  // The brain-volume gate refused: the segmentation's outline is wrong as a
  // whole (a leak into the dura, a lost lobe), and an affine fitted to it
  // carries that error as a head that shrinks or swells. Its fallback
  // delivers the affine's rigid part, as for labels whose geometry the
  // stages' gates refuse (docs/DESIGN.md "Quality gates").
  bool geometry_refused = false;
};
SegmentationGates check_segmentation(const LabelImage& segmentation, const ImageF& confidence,
                                     const LabelImage& carried_preop, const LabelTable& table,
                                     const AutoSegmentationParameters& params, double open_fluid_ml = 0);

// What the gates measure of the carried preop: the same for every round of a
// scan, so measured once. The carried preop is on the intraop grid through
// the head's placement, so its volumes count the part of the preop in the
// field of view; they are in the preop's own millilitres (the carried
// volumes divided by placement_volume_scale, the placement's determinant):
// one patient's skull does not change size between two scans, and the scale
// a placement by the head's outline finds is the two images' thresholds at
// the scalp's edge (docs/DESIGN.md "Automatic intraop segmentation", gates).
struct CarriedPreopVolumes {
  double brain_ml = 0, resectable_ml = 0, ventricles_ml = 0;
  // Below brain_ml, allowed beyond max_brain_volume_change (as the resectable
  // and the open fluid are): for given labels refined by their image, down to
  // the labels' own brain (labels_with_image.cpp). Only the gate reads it.
  double lower_allowance_ml = 0;
};
CarriedPreopVolumes carried_preop_volumes(const LabelImage& carried_preop, const LabelTable& table,
                                          double placement_volume_scale = 1.0);
SegmentationGates check_segmentation(const LabelImage& segmentation, const ImageF& confidence,
                                     const CarriedPreopVolumes& carried_preop, const LabelTable& table,
                                     const AutoSegmentationParameters& params, double open_fluid_ml);

}  // namespace brainshift
