#pragma once
// Where each tissue is expected before the image is looked at: the patient's
// own preop labels carried onto the intraop grid by the current estimate of
// the registration, softened by how far that estimate can still be off.
//   P(inside the brain) = s(-d_outline / w),  P(ventricle | inside) = s(-d_ventricle / w_v)
// with s the logistic function, d the signed distance (mm) to the carried
// outline and ventricles, and w, w_v the remaining misregistration (mm) of
// the outline and of the ventricles (deep structures shift by other amounts
// than the cortex, docs/DESIGN.md "Automatic intraop segmentation").
// When the ventricles may have moved farther than they are thick (after the
// head's alignment alone: shift_mm > 0), where they are now is not known
// within shift_mm of where they were: there
//   P(ventricle | inside) = 0.5 s(-(d_ventricle - shift_mm) / w_v),
// an even chance that the image decides (fluid or tissue), falling off beyond. A floor
// keeps parenchyma and the outside possible everywhere, so that where brain
// shift has moved tissue farther than the prior admits (fluid under the
// craniotomy, a resection cavity), the image decides.
#include <array>
#include <vector>

#include "core/image.h"
#include "image/morphology.h"

namespace brainshift::segmentation {

enum class Tissue : int { parenchyma = 0, ventricle = 1, outside = 2 };
inline constexpr int kTissues = 3;
inline int index_of(Tissue t) { return static_cast<int>(t); }
const char* name_of(Tissue t);

struct TissuePrior {
  Grid3 grid;
  std::array<std::vector<float>, kTissues> p;  // per voxel, sum to 1
  double ventricle_share = 0;  // the carried ventricles' share of the carried brain's volume
};

// outline: the brain with its ventricles (and anything inside), ventricles:
// the lateral ventricles; both on the target grid. InputError when a width
// is <= 0, floor outside [0, 0.1], or the outline is empty.
struct PriorWidths {
  double outline_mm = 3.0;   // w outside the carried outline
  // w inside it: the brain's surface sinks away from the skull under a
  // craniotomy by more than it swells past where it was.
  double inward_mm = 3.0;
  double ventricle_mm = 2.0;       // w_v
  double ventricle_shift_mm = 0;   // shift_mm
};
TissuePrior tissue_prior(const Mask& outline, const Mask& ventricles, const PriorWidths& widths, double floor);

// How far outside the carried outline the prior of width outline_mm still
// says more than its floor: where the logistic's share of the brain,
// (1 - 2 floor) s(-d / w), has fallen to the floor, d = w ln((1 - 3 floor) / floor).
// Beyond it only the floor and the image decide.
double prior_reach_mm(double outline_mm, double floor);

// The band just outside the carried outline where the prior leans to the
// outside but still allows brain (brain prior p_parenchyma + p_ventricle in
// [kSurfaceBandLow, kSurfaceBandHigh)): within about three prior widths
// outside the outline, the subarachnoid fluid and dura around the brain
// (docs/DESIGN.md "Automatic intraop segmentation", item 10). Not inside the
// outline: fluid there is sulcal, and sulci are brain (item 7).
inline constexpr double kSurfaceBandLow = 0.05, kSurfaceBandHigh = 0.5;
inline bool in_surface_band(double brain_prior) {
  return brain_prior >= kSurfaceBandLow && brain_prior < kSurfaceBandHigh;
}

}  // namespace brainshift::segmentation
