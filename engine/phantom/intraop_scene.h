#pragma once
// What an intraop scanner looks at: the deformed subject (the phantom's
// analytic deformation, brain_shift_phantom.h) as tissue classes and a
// T1-like value per voxel of a fine grid (the preop grid moved by the rigid
// head move), before any scanner blur, bias or noise (scanner_model.h).
//   - brain tissue: the preop T1 at the deformed point (ventricles, sulci and
//     a hypointense tumour keep their own T1);
//   - resection cavity: fluid, with blood settled in its dependent part
//     (ResectionSpec: blood_fill_fraction along gravity, blood_t1_relative);
//   - the gap the brain left under the craniotomy: saline up to a level
//     (gap_fluid_fraction of the cortex's sinking, from the bottom), air
//     above (no signal in any contrast);
//   - outside the brain: the head, moved rigidly; its dark voxels within
//     csf_rim_mm of the brain are subarachnoid CSF (bright on T2).
// The class decides a T2-like contrast (scanner_model.h).
#include <cstdint>

#include "core/image.h"
#include "phantom/brain_shift_phantom.h"

namespace brainshift {

enum class SceneClass : std::uint8_t { air = 0, tissue, cavity_fluid, blood, gap_fluid, head, extracerebral_csf };

struct IntraopSceneSpec {
  double gap_fluid_fraction = 0.5;
  double csf_rim_mm = 2.0;
};

struct IntraopScene {
  ImageF t1;                          // T1-like value
  Image3<std::uint8_t> classes;       // SceneClass per voxel, same grid
  // The subject's tissue levels in its preop T1 (ventricle median, 30th and
  // 85th percentiles of the brain label, brain median).
  double csf_t1 = 0, gm_t1 = 0, wm_t1 = 0, brain_median_t1 = 0;
};

// phi must be built from (preop_labels, spec) and already scaled as the case
// was (make_phantom's nonrigid_scale_applied). The pull-back is evaluated on a
// 2 mm lattice and interpolated: the scene is an image, the truth stays the
// analytic phi.
IntraopScene make_intraop_scene(const ImageF& preop_t1, const LabelImage& preop_labels, const PhantomSpec& spec,
                                const PhantomDeformation& phi, const IntraopSceneSpec& scene_spec);

}  // namespace brainshift
