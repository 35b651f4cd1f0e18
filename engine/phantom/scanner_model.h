#pragma once
// Intraop scanners: the image a given scanner makes of an intraop scene
// (intraop_scene.h). Not the preop T1 resampled: each scanner voxel
// integrates the scene over its footprint (a box in-plane, the slice profile
// across: a Gaussian of FWHM slice_profile_fwhm slice thicknesses), so thick
// slices carry partial volume; then a smooth multiplicative coil bias and
// Rician noise with the parenchyma's median signal at `snr`.
// Contrasts: T1 (the scene's values), or T2-like, set by tissue class from
// the T1 values: inside the brain a falling map through the subject's levels
// (CSF -> 1, grey matter -> 0.45, white matter -> 0.3 of the CSF signal, so a
// hypointense tumour is bright), fluid in the cavity, the gap and
// subarachnoid CSF bright, blood dark (0.35), air 0, the rest of the head at
// half its T1 value. Or a contrast-enhanced T1 (gadolinium, as an intraop
// scan that looks for residual tumour is made): the T1 with the dura
// enhancing (the head within dura_mm of the intracranial space, the gap
// and the cavity included, at 1.3 x white matter) and the resection margin
// enhancing (tissue within dura_mm of the cavity's fluid or blood, at 1.2 x
// white matter): a bright shell hugs the brain everywhere, and a bright rim
// lines the cavity, where an outline drawn by intensity leaks. Or
// FLAIR-like (fluid-attenuated inversion recovery, as many intraop
// protocols acquire): the fluid dark as on a T1 but the parenchyma ordered
// as on a T2, by the tissue's place between the subject's CSF and white
// matter on the T1 (CSF -> 0.12, grey matter at 0.7 of the way -> 0.62,
// white matter -> 0.45 of the T1's white matter), fluid in the cavity, the gap and
// subarachnoid CSF dark (0.12), blood bright (0.7), air 0, the rest of the
// head at 0.6 of its T1 value (fat stays bright). The grid is
// the phantom's (PhantomSpec dims, spacing, oblique_deg), so the truth field
// and the image share it.
#include <Eigen/Dense>
#include <random>
#include <string>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "phantom/brain_shift_phantom.h"
#include "phantom/intraop_scene.h"

namespace brainshift {

enum class Contrast { t1, t2_like, t1_contrast_enhanced, flair_like };
const char* contrast_name(Contrast c);

struct ScannerSpec {
  std::string name = "1.5T_1mm";
  Eigen::Vector3d spacing_mm{1, 1, 1};      // in-plane, in-plane, slice
  Eigen::Vector3d fov_mm{200, 230, 170};    // along the three grid axes
  Eigen::Vector3d fov_centre_offset_mm{0, 0, 0};  // world RAS+ mm, from the moved brain centroid
  Eigen::Vector3d orientation_deg{0, 0, 0}; // grid axes rotated (as PhantomSpec::oblique_deg)
  double slice_profile_fwhm = 1.0;          // in slice thicknesses
  double snr = 25;
  double bias_amplitude = 0.1;              // multiplicative, within about 1 +- this
  // A receive array instead of the polynomial bias (phantom_artefacts.h,
  // coil_array_bias): this many loops 120 mm round the brain's centre, its
  // shading raised to coil_shading. 0: the polynomial bias above.
  int coil_loops = 0;
  double coil_shading = 1.0;
  Contrast contrast = Contrast::t1;
};

// Presets for slice orientations (orientation_deg): slices across S, R, A.
Eigen::Vector3d axial_deg();
Eigen::Vector3d sagittal_deg();
Eigen::Vector3d coronal_deg();

// Writes the scanner's grid into a phantom spec (dims, spacing, obliquity).
void apply_scanner_grid(const ScannerSpec& scanner, PhantomSpec& spec);

// The contrast's value of every scene voxel (T1 or T2-like, see above).
ImageF scene_contrast(const IntraopScene& scene, Contrast contrast);

// The scanner's image on `grid` (made by apply_scanner_grid + make_phantom).
// InputError on a bad spec (spacing, SNR, bias, profile).
ImageF acquire(const IntraopScene& scene, const ScannerSpec& spec, const Grid3& grid, std::mt19937_64& rng);

nlohmann::json to_json(const ScannerSpec& spec);

}  // namespace brainshift
