#pragma once
// A second preoperative label map of the Colin27 head, made another way than
// the default atlas (atlas/default_atlas.h), so that robustness cases are not
// graded on the segmentation the engine was tuned with:
// - Brain: ch2bet > 0 with no morphological smoothing (largest 26-connected
//   component, holes filled): its outline keeps the one-voxel notches and
//   strands that the atlas opens and closes away.
// - Lateral ventricles: region growing in the ch2 T1 alone (no ch2better):
//   dark voxels of the brain eroded by erosion_mm, grown 26-connected from
//   seeds in the ventricle bodies: the surely-fluid core (T1 below csf_max),
//   then its wall out to where a voxel is half fluid (T1 below the midpoint
//   of the core's median and the median of the tissue wall_shell_mm around
//   it, within wall_shell_mm[0] of the core; on ch2 31 and 90: 60.5; growing
//   again at that level runs into sulci and deep grey). A wall at csf_max
//   instead lies about a voxel inside the fluid's partial volume: every
//   segmentation of the image, however ideal, then overshoots it by that
//   voxel (Dice about 0.72 at best, docs/PERFORMANCE.md 12.3), so the thin temporal and
//   occipital horns that leave the atlas's central box are kept. Candidates
//   below z_floor_mm (brainstem, cerebellum, fourth ventricle) and on the
//   midline below the bodies (third ventricle, cisterns) are dropped; what
//   remains connected to the bodies is kept, whatever its shape. On Colin27:
//   about 23 ml in a main part and many specks (the horns, 1-3 mm thin, are
//   connected diagonally or not at all at 1 mm).
// - Corticospinal tract: JHU white-matter labels 7/8, 15/16, 19/20, 25/26,
//   as in the atlas (the tract is carried, not matched).
// Labels: 1 brain, 2 lateral ventricles, 3 CST (same table as the atlas).
#include <array>
#include <filesystem>

#include "core/image.h"

namespace brainshift {

struct IndependentLabelParameters {
  float csf_max = 45.f;          // surely fluid; ch2: CSF ~30, grey matter ~80, white matter ~110
  bool wall_at_half_fluid = true;  // false: the wall at csf_max (the suite before docs/PERFORMANCE.md 12.3)
  // The tissue around the core: beyond the wall's partial volume (1-2 voxels),
  // within the periventricular white matter and the caudate.
  std::array<double, 2> wall_shell_mm{2.0, 5.0};
  double erosion_mm = 2.0;       // keeps cortical sulci out of the candidates
  double seed_box_half_width_mm = 20;  // seeds: |x| below this, in the bodies' box
  double z_floor_mm = -30;       // candidates below this (brainstem, cerebellum) are dropped
  // Candidates on the midline below midline_top_mm (the third ventricle, the
  // basal cisterns) are dropped: the lateral ventricles only.
  double midline_half_width_mm = 6;
  double midline_top_mm = 5;
  double min_ml = 10;            // growth must reach at least this (else a clear error)
};

struct IndependentLabels {
  LabelImage labels;  // on the T1's grid
  double brain_ml = 0, ventricles_ml = 0, cst_ml = 0;
  int ventricle_components = 0;
  double fluid_t1 = 0, tissue_t1 = 0, wall_t1 = 0;  // the core's and the tissue's medians, the wall's T1
};

// t1 = ch2.nii.gz; reads ch2bet and the JHU labels from templates_dir.
IndependentLabels build_independent_labels(const ImageF& t1, const std::filesystem::path& templates_dir,
                                           const IndependentLabelParameters& p = {});

}  // namespace brainshift
