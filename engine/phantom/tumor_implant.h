#pragma once
// A synthetic tumor put into a preop image pair, for resection cases: real
// surgery removes a segmented tumor, and the default atlas (a healthy brain)
// has none. The shape is a lobulated ball; the T1 shows it hypointense, as an
// untreated glioma looks on a non-contrast T1, with a partial-volume rim.
#include <Eigen/Dense>
#include <cstdint>
#include <optional>
#include <vector>

#include "core/image.h"

namespace brainshift {

struct TumorImplantSpec {
  // Centre: this depth (mm) below the cortex point found by a ray from the
  // brain centroid along `direction` (preop RAS), like a craniotomy site.
  Eigen::Vector3d direction{0.55, 0.7, 0.45};
  double depth_mm = 18;
  // Or here (world mm), e.g. beside a ventricle (subject_anatomy.h); then
  // direction and depth are not used.
  std::optional<Eigen::Vector3d> centre_mm;
  double radius_mm = 12;
  double lobulation = 0.15;          // relative radius variation (0 = ball)
  std::uint64_t seed = 1;
  std::uint16_t label = 4;
  // Labels the tumor may replace (tissue); others (ventricles) are kept.
  std::vector<std::uint16_t> replaceable{1, 3};
  std::vector<std::uint16_t> brain_labels{1, 2, 3, 4};
  double intensity_fraction = 0.6;   // of the brain's median T1 intensity
  // A cystic tumour: a fluid core of this fraction of the tumour's radius
  // (same lobulated shape and centre), at the median T1 of the labels in
  // `fluid_labels` (the subject's own CSF; 0.3 of the brain median without
  // them). Still the tumour label, as a segmentation of the preop draws it.
  // 0: a solid tumour.
  double cyst_radius_fraction = 0;
  std::vector<std::uint16_t> fluid_labels{2};
};

struct TumorImplantResult {
  Eigen::Vector3d centre_mm;
  double volume_ml = 0;
  double cyst_ml = 0;
};

// Modifies t1 and labels in place (same grid required). InputError when the
// grids differ, there is no brain, the ray finds no cortex or the tumor would
// take no voxel.
TumorImplantResult implant_tumor(ImageF& t1, LabelImage& labels, const TumorImplantSpec& spec);

}  // namespace brainshift
