#pragma once
// Open fluid: fluid the classifier took into the brain that is a body of
// fluid open to the outside (the gap under a sunken cortex, a cavity open to
// the surface), moved out of the brain with the caps beyond it
// (docs/DESIGN.md "Automatic intraop segmentation", item 7).
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "core/image.h"
#include "image/image_stats.h"
#include "segmentation/tissue_em.h"

namespace brainshift::segmentation {

// The preop as it was before the operation, where the head's placement puts
// it on the intraop grid: fluid the preop already held there (a cistern, a
// fissure) is anatomy, not a gap a sinking opened (open_fluid).
struct PreopSeen {
  const ImageF* image = nullptr;  // the preop T1 (its own grid)
  Eigen::Matrix4d preop_from_intraop = Eigen::Matrix4d::Identity();  // world mm
  double fluid_median = 0;   // the preop's intensity in its ventricles
  double tissue_median = 0;  // and in its parenchyma
  Mask resectable;           // the carried preop's resectable labels, intraop grid (empty: none)
};

// The gap a sinking left that the classification itself called outside:
// fluid (bias-corrected intensity within 2 sd of the fluid class's mean,
// where 95 % of its voxels lie, and nearer it than any parenchyma class's,
// which keeps the cortex's partial volume out) inside the carried outline, outside
// the classified brain (before open_fluid and the rim move anything) and
// ventricles, thicker than any sulcus (it survives an opening of radius
// max_sulcus_half_width_mm), in bodies of at least min_gap_ml touching the
// carried outline's surface. Where no parenchyma class spans the fluid (a
// FLAIR-like image: tissue_em.h), the gap never enters the brain, so the
// open-fluid rule (open_fluid) never moves it out nor counts it; the brain-volume
// gate allows for it as for the fluid that rule moves (docs/PERFORMANCE.md
// 12.37). Returns its volume, ml.
double gap_left_outside_ml(const ImageF& image, const std::vector<float>& bias, const std::vector<GaussianClass>& classes,
                           const Mask& brain, const Mask& ventricle, const Mask& carried_outline,
                           double max_sulcus_half_width_mm, double min_gap_ml);

// Fluid labelled parenchyma that is thicker than any sulcus (it survives an
// opening of radius max_sulcus_half_width_mm) and lies open to what is
// outside the brain (at most a cap, drop_beyond_open_fluid, between) is not
// in the brain: the gap a sunken cortex leaves under the craniotomy, a cavity
// open to the surface.
// The prior, carried from where the brain was, holds brain there, and a
// parenchyma class stretched over the sulci's fluid and partial volume
// explains the fluid as well as the fluid class does: the image alone does
// not move it out, its shape does. Returns the voxels moved out.
struct OpenFluid {
  Mask moved;                          // the gap's fluid, moved out of the brain
  double next_to_ventricles_ml = 0;    // thick fluid left in: continuous with the ventricles
  double partial_fluid_ml = 0;         // left in: its median, or its raw ratio to the tissue beside it, nearer the turn
  double fluid_before_ml = 0;          // left in: fluid in the preop as well (a cistern, a fissure)
  nlohmann::json components = nlohmann::json::array();  // diagnostic: each open component >= min_gap_ml
};
OpenFluid open_fluid(const ImageF& image, const std::vector<float>& bias, const std::vector<GaussianClass>& classes,
                     const Mask& brain, const Mask& ventricle, const Mask& carried_ventricles,
                     const Mask& carried_outline, double max_sulcus_half_width_mm, double max_cap_mm,
                     double min_gap_ml, double max_median_toward_turn, const PreopSeen* seen,
                     const Mask& resectable, double min_preop_toward_tissue);

// A re-match sees the same image as the round before, under a prior carried
// by the non-rigid estimate instead of the head's placement. The gap a
// sinking leaves is centimetres wide and open to the craniotomy: the first
// round, under the wider prior, finds it too. What only the re-match calls
// open fluid lies where its narrower prior moved the outline onto fluid the
// brain borders anyway: the basal cisterns and the floor of the third
// ventricle under a swelling (docs/PERFORMANCE.md 12.9, 12.10), whose
// removal notched the outline and moved the field by up to 9 mm there. So a
// component of open fluid stands in the re-match only where it touches the
// gap found before, grown by a sulcus's half width (the same fluid, its
// edge classified a voxel apart). `moved` lies on `box` of found_before's
// grid (an empty grid: no gap was found before).
void keep_gaps_found_before(Mask& moved, const Mask& found_before, const VoxelBox& box, double max_sulcus_half_width_mm);

// Tissue on the far side of open fluid, between it and the skull (the dura,
// the inner table and their partial volume, cut obliquely by thick slices),
// is not brain either: the brain lies beneath the gap a sinking leaves, never
// beyond it. Along the ray through a brain voxel toward the carried brain's
// centre: fluid moved out on the inner side and what is outside the brain on
// the outer side, with less than max_cap_mm of brain between them, is such a
// cap. The cortex beneath the gap and gyri rising into it look inward into
// brain; a lobe beyond a cistern is thicker than a cap.
void drop_beyond_open_fluid(Mask& brain, const Mask& ventricle, const Mask& moved, const Eigen::Vector3d& centre_voxel,
                            double max_cap_mm, double max_sulcus_half_width_mm);

}  // namespace brainshift::segmentation
