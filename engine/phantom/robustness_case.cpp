#include "phantom/robustness_case.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <random>
#include <set>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "phantom/phantom_artefacts.h"
#include "phantom/phantom_support.h"

namespace brainshift {
namespace {

using phantom_detail::quantile;

void check(const RobustnessSpec& s) {
  const auto& g = s.segmentation;
  const auto& i = s.image;
  if (!(g.boundary_noise_voxels >= 0 && g.boundary_noise_voxels <= 5 && g.correlation_mm > 0 && g.islands >= 0 &&
        g.holes >= 0 && g.blob_radius_mm > 0 && g.blob_radius_mm <= 10))
    throw InputError("robustness case '" + s.phantom.name +
                     "': segmentation artefacts need noise in [0,5] voxels, positive correlation, blob radius in (0,10] mm");
  if (!(i.gm_wm_contrast > 0 && i.gm_wm_contrast <= 1 && i.bias_amplitude >= 0 && i.bias_amplitude < 1 &&
        i.wm_snr > 0 && i.slice_fwhm_slices >= 0))
    throw InputError("robustness case '" + s.phantom.name +
                     "': image artefacts need contrast in (0,1], bias in [0,1), positive SNR, slice FWHM >= 0");
}

// Thresholds a structure's signed distance plus smooth noise: a boundary moved
// by the noise, as a segmenter's would be.
Mask noisy(const Mask& clean, const std::vector<float>& noise_mm) {
  const ImageF sd = signed_distance_mm(clean);
  Mask out(clean.grid, 0);
  for (std::size_t v = 0; v < out.voxels.size(); ++v) out.voxels[v] = sd.voxels[v] + noise_mm[v] < 0;
  return out;
}

// Sets the label of every voxel within radius of a centre.
void paint_ball(LabelImage& labels, const Eigen::Vector3d& centre_mm, double radius_mm, std::uint16_t value) {
  const Grid3& g = labels.grid;
  const Eigen::Vector3d c = (g.voxel_from_world() * centre_mm.homogeneous()).head<3>();
  const Eigen::Vector3d sp = g.spacing_mm();
  int lo[3], hi[3];
  for (int d = 0; d < 3; ++d) {
    const double r = radius_mm / sp[d] + 1;
    lo[d] = std::max(0, static_cast<int>(std::floor(c[d] - r)));
    hi[d] = std::min(g.dims[d] - 1, static_cast<int>(std::ceil(c[d] + r)));
  }
  for (int k = lo[2]; k <= hi[2]; ++k)
    for (int j = lo[1]; j <= hi[1]; ++j)
      for (int i = lo[0]; i <= hi[0]; ++i)
        if ((g.world_mm(i, j, k) - centre_mm).norm() <= radius_mm) labels.at(i, j, k) = value;
}

// Random voxel centres where pick(v) holds (rejection sampling, bounded).
std::vector<Eigen::Vector3d> random_sites(const Grid3& g, int count, std::mt19937_64& rng,
                                          const std::function<bool(std::size_t)>& pick) {
  std::vector<Eigen::Vector3d> out;
  std::uniform_int_distribution<std::size_t> any(0, g.voxel_count() - 1);
  for (std::size_t tries = 0; static_cast<int>(out.size()) < count && tries < 200000; ++tries) {
    const std::size_t v = any(rng);
    if (!pick(v)) continue;
    const int i = static_cast<int>(v % g.dims[0]), j = static_cast<int>((v / g.dims[0]) % g.dims[1]),
              k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    out.push_back(g.world_mm(i, j, k));
  }
  return out;
}

LabelImage degrade_segmentation(const LabelImage& clean, const SegmentationArtefacts& a, std::mt19937_64& rng) {
  const Grid3& g = clean.grid;
  const Eigen::Vector3d sp = g.spacing_mm();
  const double voxel_mm = std::min({sp[0], sp[1], sp[2]});
  const double rms_mm = a.boundary_noise_voxels * voxel_mm;
  const Mask brain = noisy(nonzero_mask(clean), smooth_noise(g, a.correlation_mm, rms_mm, rng));
  const Mask vent = noisy(mask_of_labels(clean, {2}), smooth_noise(g, a.correlation_mm, rms_mm, rng));
  LabelImage out(g, 0);
  for (std::size_t v = 0; v < out.voxels.size(); ++v) out.voxels[v] = brain.voxels[v] ? (vent.voxels[v] ? 2 : 1) : 0;

  // Distances of the clean structures pick where islands and holes go.
  const ImageF sd_brain = signed_distance_mm(nonzero_mask(clean));
  const ImageF sd_vent = signed_distance_mm(mask_of_labels(clean, {2}));
  std::uniform_real_distribution<double> radius(0.6 * a.blob_radius_mm, 1.4 * a.blob_radius_mm);
  const int half_islands = a.islands / 2, half_holes = a.holes / 2;
  for (const auto& c : random_sites(g, a.islands - half_islands, rng, [&](std::size_t v) {
         return sd_brain.voxels[v] > 1.5 && sd_brain.voxels[v] < 6;  // specks beside the brain
       }))
    paint_ball(out, c, radius(rng), 1);
  for (const auto& c : random_sites(g, half_islands, rng, [&](std::size_t v) {
         return sd_vent.voxels[v] > 2 && sd_vent.voxels[v] < 8 && sd_brain.voxels[v] < -5;  // CSF-like specks in white matter
       }))
    paint_ball(out, c, radius(rng), 2);
  for (const auto& c : random_sites(g, a.holes - half_holes, rng, [&](std::size_t v) {
         return sd_brain.voxels[v] < -3 && sd_vent.voxels[v] > 3;  // dark spots read as background
       }))
    paint_ball(out, c, radius(rng), 0);
  for (const auto& c : random_sites(g, half_holes, rng, [&](std::size_t v) {
         return sd_vent.voxels[v] < -1;  // choroid plexus read as tissue
       }))
    paint_ball(out, c, radius(rng), 1);
  return out;
}

ImageF degrade_image(const ImageF& clean, const LabelImage& clean_labels, const ImageArtefacts& a, std::mt19937_64& rng) {
  std::vector<float> tissue;
  for (std::size_t v = 0; v < clean.voxels.size(); ++v)
    if (clean_labels.voxels[v] == 1) tissue.push_back(clean.voxels[v]);
  // Grey matter about the 30th percentile of tissue, white matter the 85th.
  const double gm = quantile(tissue, 0.30), wm = quantile(tissue, 0.85);
  ImageF out = clean;
  for (auto& v : out.voxels)
    if (v > gm) v = static_cast<float>(gm + a.gm_wm_contrast * (v - gm));
  gaussian_smooth_voxels(out, Eigen::Vector3d(0, 0, a.slice_fwhm_slices / 2.3548));
  const auto bias = bias_field(out.grid, std::log1p(a.bias_amplitude), rng);
  for (std::size_t v = 0; v < out.voxels.size(); ++v) out.voxels[v] *= bias[v];
  const double wm_level = gm + a.gm_wm_contrast * (wm - gm);
  add_rician_noise(out.voxels, wm_level / a.wm_snr, rng);
  return out;
}

}  // namespace

PhantomCase make_robustness_case(const ImageF& t1, const LabelImage& truth_labels, const RobustnessSpec& spec) {
  check(spec);
  PhantomSpec clean = spec.phantom;
  clean.label_noise_mm = 0;
  clean.noise_fraction = 0;
  clean.bias_amplitude = 0;
  PhantomCase c = make_phantom(t1, truth_labels, clean);
  std::mt19937_64 rng(spec.phantom.seed * 7919 + 17);
  const LabelImage clean_labels = c.intraop_labels;
  c.intraop_labels = degrade_segmentation(clean_labels, spec.segmentation, rng);
  c.intraop_t1 = degrade_image(c.intraop_t1, clean_labels, spec.image, rng);
  const auto& s = spec.segmentation;
  const auto& i = spec.image;
  c.description["robustness"] = {
      {"segmentation", {{"boundary_noise_voxels", s.boundary_noise_voxels}, {"correlation_mm", s.correlation_mm},
                        {"islands", s.islands}, {"holes", s.holes}, {"blob_radius_mm", s.blob_radius_mm}}},
      {"image", {{"gm_wm_contrast", i.gm_wm_contrast}, {"bias_amplitude", i.bias_amplitude}, {"wm_snr", i.wm_snr},
                 {"slice_fwhm_slices", i.slice_fwhm_slices}}},
      {"preop_is_truth", spec.preop_is_truth}};
  return c;
}

namespace {

RobustnessSpec robust(const std::string& name, std::uint64_t seed, bool preop_is_truth, double noise_voxels,
                      double correlation_mm) {
  RobustnessSpec r;
  r.phantom.name = name;
  r.phantom.seed = seed;
  r.preop_is_truth = preop_is_truth;
  r.segmentation.boundary_noise_voxels = noise_voxels;
  r.segmentation.correlation_mm = correlation_mm;
  return r;
}

// Grid orientations: LAS (first axis flipped), RAS, coronal slices, oblique.
void las(PhantomSpec& s) { s.flip_first_axis = true; }
void coronal(PhantomSpec& s) {
  s.oblique_deg = {90, 0, 0};  // the slice axis along -A
  s.dims = {256, 256, 72};
}
void oblique(PhantomSpec& s, const Eigen::Vector3d& deg) { s.oblique_deg = deg; }

TumorImplantSpec tumor_under(const Eigen::Vector3d& direction, std::uint64_t seed) {
  TumorImplantSpec t;
  t.direction = direction;
  t.depth_mm = 18;
  t.radius_mm = 11;
  t.seed = seed;
  return t;
}

}  // namespace

std::vector<RobustnessSpec> robustness_suite() {
  std::vector<RobustnessSpec> suite;
  {
    RobustnessSpec r = robust("frontal_sinking_10mm_las_noise1.0_short", 101, true, 1.0, 3);
    r.phantom.sinking.craniotomy_direction = {-0.5, 0.75, 0.45};
    r.phantom.sinking.gravity = Eigen::Vector3d(0.3, -0.8, -0.5);
    r.phantom.sinking.cortex_mm = 10;
    las(r.phantom);
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("parietal_sinking_16mm_ras_noise0.5_long", 102, false, 0.5, 15);
    r.phantom.sinking.craniotomy_direction = {0.6, -0.5, 0.6};
    r.phantom.sinking.gravity = Eigen::Vector3d(-0.8, 0.2, -0.55);
    r.phantom.sinking.cortex_mm = 16;
    r.phantom.sinking.deep_mm = 3;
    r.phantom.sinking.depth_decay_mm = 35;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("vertex_sinking_18mm_coronal_noise1.5_short", 103, true, 1.5, 2.5);
    r.phantom.sinking.craniotomy_direction = {0.15, -0.1, 1.0};
    r.phantom.sinking.gravity = Eigen::Vector3d(0, 0, -1);
    r.phantom.sinking.cortex_mm = 18;
    r.phantom.sinking.deep_mm = 4;
    r.phantom.sinking.depth_decay_mm = 40;
    coronal(r.phantom);
    r.image.wm_snr = 12;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("temporal_sinking_12mm_oblique_noise1.0_long", 104, false, 1.0, 12);
    r.phantom.sinking.craniotomy_direction = {-1.0, 0.1, -0.2};
    r.phantom.sinking.gravity = Eigen::Vector3d(1, 0, 0);
    r.phantom.sinking.cortex_mm = 12;
    r.phantom.sinking.deep_mm = 3;
    r.phantom.rigid.rotation_deg = {-4, 3, -2};
    r.phantom.rigid.translation_mm = {-3, 2, -2};
    oblique(r.phantom, {-12, 8, 5});
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("deep_swelling_4mm_ras_noise1.0_short", 105, true, 1.0, 4);
    r.phantom.sinking.enabled = false;
    r.phantom.swelling.enabled = true;
    r.phantom.swelling.amplitude_mm = 4;
    r.phantom.swelling.centre_offset_mm = {-25, 10, 15};
    r.image.bias_amplitude = 0.2;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("swelling_and_sinking_las_oblique_noise1.5_long", 106, false, 1.5, 18);
    r.phantom.sinking.craniotomy_direction = {0.55, 0.6, 0.55};
    r.phantom.sinking.cortex_mm = 8;
    r.phantom.swelling.enabled = true;
    r.phantom.swelling.amplitude_mm = 3;
    r.phantom.swelling.centre_offset_mm = {25, 15, 20};
    las(r.phantom);
    oblique(r.phantom, {8, -6, 10});
    r.image.wm_snr = 18;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("frontal_resection_ras_noise1.0_short", 107, true, 1.0, 3);
    r.phantom.sinking.craniotomy_direction = {0.55, 0.7, 0.45};
    r.phantom.sinking.cortex_mm = 8;
    r.phantom.preop_tumor = tumor_under(r.phantom.sinking.craniotomy_direction, 107);
    r.phantom.resection.enabled = true;
    r.phantom.resection.collapse_mm = 4;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("parietal_resection_coronal_noise0.5_long", 108, false, 0.5, 10);
    r.phantom.sinking.craniotomy_direction = {-0.6, -0.4, 0.7};
    r.phantom.sinking.cortex_mm = 10;
    r.phantom.preop_tumor = tumor_under(r.phantom.sinking.craniotomy_direction, 108);
    r.phantom.resection.enabled = true;
    r.phantom.resection.collapse_mm = 5;
    coronal(r.phantom);
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("occipital_sinking_8mm_rigid_las_noise1.5_short", 109, true, 1.5, 3);
    r.phantom.sinking.craniotomy_direction = {0.1, -1.0, 0.2};
    r.phantom.sinking.gravity = Eigen::Vector3d(0, 1, 0);
    r.phantom.sinking.cortex_mm = 8;
    r.phantom.rigid.rotation_deg = {3, -2, 4};
    r.phantom.rigid.translation_mm = {2, -3, 1.5};
    las(r.phantom);
    r.image.gm_wm_contrast = 0.45;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("frontal_sinking_14mm_oblique_noise0.5_short", 110, false, 0.5, 2);
    r.phantom.sinking.craniotomy_direction = {0.4, 0.85, 0.35};
    r.phantom.sinking.cortex_mm = 14;
    r.phantom.sinking.deep_mm = 3;
    oblique(r.phantom, {15, 0, -10});
    r.image.wm_snr = 12;
    r.image.slice_fwhm_slices = 2.0;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("vertex_sinking_12mm_ras_noise1.0_long", 111, true, 1.0, 20);
    r.phantom.sinking.craniotomy_direction = {-0.2, 0.1, 1.0};
    r.phantom.sinking.gravity = Eigen::Vector3d(0, 0, -1);
    r.phantom.sinking.cortex_mm = 12;
    suite.push_back(r);
  }
  {
    RobustnessSpec r = robust("temporal_swelling_coronal_noise1.0_short", 112, false, 1.0, 5);
    r.phantom.sinking.craniotomy_direction = {1.0, 0.0, -0.1};
    r.phantom.sinking.gravity = Eigen::Vector3d(-1, 0, 0);
    r.phantom.sinking.cortex_mm = 9;
    r.phantom.swelling.enabled = true;
    r.phantom.swelling.amplitude_mm = 2.5;
    r.phantom.swelling.centre_offset_mm = {30, 0, -5};
    coronal(r.phantom);
    r.image.bias_amplitude = 0.3;
    suite.push_back(r);
  }
  {
    // A lateral approach: the head turned 70 degrees in its clamp (and
    // flexed), which the scanner's RAS does not follow; the craniotomy
    // uppermost, gravity toward the other side.
    RobustnessSpec r = robust("temporal_sinking_10mm_head_turned_70_noise1.0_short", 113, true, 1.0, 4);
    r.phantom.sinking.craniotomy_direction = {-1.0, 0.15, 0.2};
    r.phantom.sinking.gravity = Eigen::Vector3d(1, 0, 0);
    r.phantom.sinking.cortex_mm = 10;
    r.phantom.sinking.deep_mm = 3;
    r.phantom.rigid.rotation_deg = {12, -5, 70};
    r.phantom.rigid.translation_mm = {15, -25, 10};
    r.image.wm_snr = 15;
    suite.push_back(r);
  }
  return suite;
}

std::vector<RobustnessSpec> robustness_suite_cases(const std::vector<std::string>& names) {
  std::vector<RobustnessSpec> suite = robustness_suite();
  if (names.empty()) return suite;
  const std::set<std::string> want(names.begin(), names.end());
  std::erase_if(suite, [&](const RobustnessSpec& s) { return !want.count(s.phantom.name); });
  return suite;
}

RobustnessSpec robustness_turned_head_case() { return robustness_suite().back(); }

std::vector<RobustnessSpec> robustness_ci_subset() {
  const auto all = robustness_suite();
  return {all[0], all[3]};
}

}  // namespace brainshift
