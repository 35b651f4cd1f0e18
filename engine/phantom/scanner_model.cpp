// Scanner image synthesis (scanner_model.h).
#include "phantom/scanner_model.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/resample.h"
#include "phantom/phantom_artefacts.h"
#include "phantom/phantom_support.h"

namespace brainshift {
namespace {

using namespace phantom_detail;

void check(const ScannerSpec& s) {
  if (!(s.spacing_mm.minCoeff() >= 0.3 && s.spacing_mm.maxCoeff() <= 8 && s.fov_mm.minCoeff() >= 10 &&
        s.fov_mm.maxCoeff() <= 400 && s.slice_profile_fwhm >= 0.3 && s.slice_profile_fwhm <= 3 && s.snr > 0 &&
        s.bias_amplitude >= 0 && s.bias_amplitude < 1 && s.fov_centre_offset_mm.allFinite() &&
        s.fov_centre_offset_mm.norm() <= 200 && s.coil_loops >= 0 && s.coil_loops <= 64 && s.coil_shading >= 0 &&
        s.coil_shading <= 2))
    throw InputError("scanner '" + s.name + "': spacing in [0.3, 8] mm, FOV in [10, 400] mm, its centre within "
                     "200 mm of the brain's, slice profile in [0.3, 3] slices, SNR > 0, bias in [0, 1), 0-64 coil "
                     "loops and a coil shading in [0, 2] are required");
}

// T2-like value of brain tissue from its T1: piecewise linear through
// (CSF, 1), (GM, 0.45), (WM, 0.3), flat beyond; times the CSF reference.
double t2_of_tissue(double t1, const IntraopScene& s, double reference) {
  const double xs[3] = {s.csf_t1, s.gm_t1, s.wm_t1}, ys[3] = {1.0, 0.45, 0.3};
  if (t1 <= xs[0]) return reference * ys[0];
  if (t1 >= xs[2]) return reference * ys[2];
  const int seg = t1 < xs[1] ? 0 : 1;
  const double f = (t1 - xs[seg]) / std::max(1e-9, xs[seg + 1] - xs[seg]);
  return reference * (ys[seg] + f * (ys[seg + 1] - ys[seg]));
}

// FLAIR-like value of brain tissue from its T1, by its place r between the
// subject's CSF (0) and white matter (1) on the T1: piecewise linear
// through (0, 0.12), (0.7, 0.62), (1, 0.45), flat beyond; times the
// reference (white matter's T1). Grey matter sits at about 0.7 of the way
// on a T1 (0.8 of white matter with CSF at 0.3); the subject's 30th
// percentile is not used: on a brain mostly white it is white matter.
double flair_of_tissue(double t1, const IntraopScene& s, double reference) {
  constexpr double kGreyPlace = 0.7;
  const double r = std::clamp((t1 - s.csf_t1) / std::max(1e-9, s.wm_t1 - s.csf_t1), 0.0, 1.0);
  const double y = r < kGreyPlace ? 0.12 + (0.62 - 0.12) * r / kGreyPlace
                                  : 0.62 + (0.45 - 0.62) * (r - kGreyPlace) / (1 - kGreyPlace);
  return reference * y;
}

// Levels of the non-tissue scene classes, as fractions of the reference
// (white matter's T1 signal), and the rest of the head as a fraction of its
// own T1 value.
struct ClassLevels {
  double fluid, blood, head_of_t1;
};

// A contrast set by scene class: the brain's tissue through tissue_value
// (from its T1), the fluid in the cavity, the gap and the subarachnoid space,
// blood and the head at their levels, air 0.
ImageF by_scene_class(const IntraopScene& scene, double (*tissue_value)(double, const IntraopScene&, double),
                      const ClassLevels& levels) {
  ImageF out(scene.t1.grid, 0.f);
  const double reference = scene.wm_t1;
  for (std::size_t v = 0; v < out.voxels.size(); ++v) {
    const double t1 = scene.t1.voxels[v];
    double value = 0;
    switch (static_cast<SceneClass>(scene.classes.voxels[v])) {
      case SceneClass::tissue: value = tissue_value(t1, scene, reference); break;
      case SceneClass::cavity_fluid:
      case SceneClass::gap_fluid:
      case SceneClass::extracerebral_csf: value = levels.fluid * reference; break;
      case SceneClass::blood: value = levels.blood * reference; break;
      case SceneClass::head: value = levels.head_of_t1 * t1; break;
      case SceneClass::air: value = 0; break;
    }
    out.voxels[v] = static_cast<float>(value);
  }
  return out;
}

// Gadolinium: the dura's and the resection margin's enhancement (see the
// header). Thickness 1.5 mm: the dura is about 1 mm, and enhancement of the
// margin a millimetre or two; the scene grid resolves it.
ImageF contrast_enhanced(const IntraopScene& scene) {
  constexpr double kShellMm = 1.5, kDura = 1.3, kMargin = 1.2;
  ImageF out = scene.t1;
  const Grid3& g = scene.classes.grid;
  Mask intracranial(g, 0), cavity(g, 0);
  for (std::size_t v = 0; v < intracranial.voxels.size(); ++v) {
    const auto c = static_cast<SceneClass>(scene.classes.voxels[v]);
    intracranial.voxels[v] = c != SceneClass::head && c != SceneClass::air;
    cavity.voxels[v] = c == SceneClass::cavity_fluid || c == SceneClass::blood;
  }
  const ImageF from_intracranial = distance_to_mask_mm(intracranial, 2 * kShellMm);
  const ImageF from_cavity = distance_to_mask_mm(cavity, 2 * kShellMm);
  for (std::size_t v = 0; v < out.voxels.size(); ++v) {
    const auto c = static_cast<SceneClass>(scene.classes.voxels[v]);
    if (c == SceneClass::head && from_intracranial.voxels[v] <= kShellMm)
      out.voxels[v] = static_cast<float>(kDura * scene.wm_t1);
    else if (c == SceneClass::tissue && from_cavity.voxels[v] <= kShellMm)
      out.voxels[v] = static_cast<float>(kMargin * scene.wm_t1);
  }
  return out;
}

}  // namespace

const char* contrast_name(Contrast c) {
  switch (c) {
    case Contrast::t1: return "t1";
    case Contrast::t2_like: return "t2_like";
    case Contrast::t1_contrast_enhanced: return "t1_contrast_enhanced";
    case Contrast::flair_like: return "flair_like";
  }
  return "?";
}

Eigen::Vector3d axial_deg() { return {0, 0, 0}; }
Eigen::Vector3d sagittal_deg() { return {0, 90, 0}; }  // third axis along R
Eigen::Vector3d coronal_deg() { return {90, 0, 0}; }   // third axis along -A

void apply_scanner_grid(const ScannerSpec& scanner, PhantomSpec& spec) {
  check(scanner);
  for (int a = 0; a < 3; ++a) spec.dims[a] = std::max(2, static_cast<int>(std::lround(scanner.fov_mm[a] / scanner.spacing_mm[a])));
  spec.spacing_mm = scanner.spacing_mm;
  spec.oblique_deg = scanner.orientation_deg;
  spec.grid_centre_offset_mm = scanner.fov_centre_offset_mm;
}

ImageF scene_contrast(const IntraopScene& scene, Contrast contrast) {
  if (contrast == Contrast::t1) return scene.t1;
  if (contrast == Contrast::t1_contrast_enhanced) return contrast_enhanced(scene);
  if (contrast == Contrast::flair_like) return by_scene_class(scene, flair_of_tissue, {0.12, 0.7, 0.6});
  // T2-like: the CSF signal sets the scale, as bright as white matter is on
  // the T1; blood dark, the head at half its T1 value.
  return by_scene_class(scene, t2_of_tissue, {1.0, 0.35, 0.5});
}

ImageF acquire(const IntraopScene& scene, const ScannerSpec& spec, const Grid3& grid, std::mt19937_64& rng) {
  check(spec);
  const ImageF contrast = scene_contrast(scene, spec.contrast);
  const double scene_mm = scene.t1.grid.spacing_mm().minCoeff();
  const Eigen::Vector3d sp = grid.spacing_mm();
  // Sub-samples of a voxel (voxel-coordinate offsets and weights): a box
  // in-plane, the Gaussian slice profile over +-1.5 FWHM across.
  std::vector<std::pair<Eigen::Vector3d, double>> taps;
  const int n0 = std::max(1, static_cast<int>(std::lround(sp[0] / scene_mm)));
  const int n1 = std::max(1, static_cast<int>(std::lround(sp[1] / scene_mm)));
  const double fwhm_mm = spec.slice_profile_fwhm * sp[2];
  const int ns = std::max(1, static_cast<int>(std::ceil(3 * fwhm_mm / scene_mm)));
  const double sigma_mm = fwhm_mm / 2.3548;
  double total = 0;
  for (int a = 0; a < n0; ++a)
    for (int b = 0; b < n1; ++b)
      for (int c = 0; c < ns; ++c) {
        const double t_mm = ns == 1 ? 0.0 : -1.5 * fwhm_mm + (c + 0.5) * 3 * fwhm_mm / ns;
        const double w = std::exp(-0.5 * t_mm * t_mm / (sigma_mm * sigma_mm));
        taps.emplace_back(Eigen::Vector3d((a + 0.5) / n0 - 0.5, (b + 0.5) / n1 - 0.5, t_mm / sp[2]), w);
        total += w;
      }
  for (auto& t : taps) t.second /= total;

  ImageF out(grid, 0.f);
  const GridSampler scene_sampler(contrast.grid);
  parallel_slices(grid.dims[2], [&](int k) {
    for (int j = 0; j < grid.dims[1]; ++j)
      for (int i = 0; i < grid.dims[0]; ++i) {
        double acc = 0;
        for (const auto& [offset, w] : taps)
          acc += w * scene_sampler.linear(contrast.voxels, grid.world_mm(i + offset.x(), j + offset.y(), k + offset.z()), 0.f);
        out.at(i, j, k) = static_cast<float>(acc);
      }
  });
  // The array's centre: the brain's, where the field of view was centred
  // before its offset (a head coil holds the head, not the field of view).
  const Eigen::Vector3d grid_centre_mm =
      grid.world_mm(0.5 * (grid.dims[0] - 1), 0.5 * (grid.dims[1] - 1), 0.5 * (grid.dims[2] - 1));
  const auto bias = spec.coil_loops > 0
                        ? coil_array_bias(grid, grid_centre_mm - spec.fov_centre_offset_mm, spec.coil_loops, 120, 45,
                                          60, spec.coil_shading, rng)
                        : bias_field(grid, std::log1p(spec.bias_amplitude), rng);
  for (std::size_t v = 0; v < out.voxels.size(); ++v) out.voxels[v] *= bias[v];
  std::vector<float> parenchyma;
  for (std::size_t v = 0; v < contrast.voxels.size(); ++v)
    if (scene.classes.voxels[v] == static_cast<std::uint8_t>(SceneClass::tissue)) parenchyma.push_back(contrast.voxels[v]);
  const double reference = quantile(parenchyma, 0.5);
  if (reference > 0) add_rician_noise(out.voxels, reference / spec.snr, rng);
  return out;
}

nlohmann::json to_json(const ScannerSpec& s) {
  auto vec = [](const Eigen::Vector3d& v) { return nlohmann::json::array({v.x(), v.y(), v.z()}); };
  return {{"name", s.name}, {"spacing_mm", vec(s.spacing_mm)}, {"fov_mm", vec(s.fov_mm)}, {"fov_centre_offset_mm", vec(s.fov_centre_offset_mm)},
          {"orientation_deg", vec(s.orientation_deg)}, {"slice_profile_fwhm", s.slice_profile_fwhm},
          {"snr", s.snr}, {"bias_amplitude", s.bias_amplitude},
          {"coil_loops", s.coil_loops}, {"coil_shading", s.coil_shading},
          {"contrast", contrast_name(s.contrast)}};
}

}  // namespace brainshift
