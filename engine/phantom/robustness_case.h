#pragma once
// Robustness cases: brain shift as an independent segmenter and a low-field
// scanner would show it, not as the engine's own phantom does.
//
// The deformation is the phantom's analytic one (brain_shift_phantom.h:
// sinking, swelling, resection, rigid move; not the engine's elastic model).
// The intraop segmentation is the deformed TRUTH label map (which need not be
// the preop map the engine registers, e.g. the independent map of
// independent_labels.h), degraded as fast segmenters degrade it:
//   - boundary noise: the signed distance of every structure plus a smooth
//     random field of boundary_noise_voxels RMS (in voxels of the intraop
//     in-plane spacing) and correlation length correlation_mm (2-5 mm: ragged;
//     10-20 mm: a wavy, biased outline);
//   - islands and holes: small balls of the wrong label next to the brain,
//     inside it and in and around the ventricles.
// The intraop T1 is not the preop T1 resampled: GM/WM contrast compressed
// (values above the grey-matter level scaled by gm_wm_contrast), a smooth bias
// of +-bias_amplitude, the slice profile blurred across slices (Gaussian of
// FWHM slice_fwhm_slices), Rician noise with white matter at wm_snr, and fluid
// where the brain pulled away from the skull and in the cavity (as in the
// phantom).
#include <string>
#include <vector>

#include "phantom/brain_shift_phantom.h"

namespace brainshift {

struct SegmentationArtefacts {
  double boundary_noise_voxels = 1.0;
  double correlation_mm = 3.0;
  int islands = 6;            // false-positive balls of brain outside it, of ventricle in white matter
  int holes = 6;              // false-negative balls inside the brain and the ventricles
  double blob_radius_mm = 1.5;
};

struct ImageArtefacts {
  double gm_wm_contrast = 0.6;   // fraction of the intensity range above grey matter kept
  double bias_amplitude = 0.3;   // multiplicative, about 1 +- this
  double wm_snr = 15;            // white-matter intensity / Rician sigma
  double slice_fwhm_slices = 1.5;
};

struct RobustnessSpec {
  PhantomSpec phantom;           // deformation and grid; its own noise settings are not used
  SegmentationArtefacts segmentation;
  ImageArtefacts image;
  bool preop_is_truth = false;   // register against the truth map (else against the other preop)
};

// truth_labels: the anatomy the intraop segmentation is made from (same grid
// as t1). InputError on bad specs (see make_phantom) or artefact values.
PhantomCase make_robustness_case(const ImageF& t1, const LabelImage& truth_labels, const RobustnessSpec& spec);

// Thirteen cases over two preop maps, 0.5-1.5 voxel noise of short and long
// correlation, LAS / RAS / coronal / oblique grids, sinking, swelling and
// resection, and a head turned 70 degrees in its clamp. ci_subset: the few CI
// runs; turned_head_case: the last.
std::vector<RobustnessSpec> robustness_suite();
std::vector<RobustnessSpec> robustness_ci_subset();
RobustnessSpec robustness_turned_head_case();
// The suite's cases named in `names`, in the suite's order (all when empty).
std::vector<RobustnessSpec> robustness_suite_cases(const std::vector<std::string>& names);

}  // namespace brainshift
