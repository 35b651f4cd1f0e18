// The hospital-variation suite (hospital_suite.h): subjects, cases, and the
// making of one case.
#include "phantom/hospital_suite.h"

#include <chrono>
#include <random>

#include "core/errors.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "image/resample.h"

namespace brainshift {
namespace {

SubjectSpec subject(const std::string& name, std::uint64_t seed, const Eigen::Vector3d& scale, int bumps,
                    double amplitude_mm, double width_mm) {
  SubjectSpec s;
  s.name = name;
  s.seed = seed;
  s.axis_scale = scale;
  s.reshape_bumps = bumps;
  s.reshape_amplitude_mm = amplitude_mm;
  s.reshape_width_mm = width_mm;
  return s;
}

// Craniotomy sites with the gravity of the usual patient position.
void frontal_left(SinkingSpec& s) {
  s.craniotomy_direction = {-0.5, 0.75, 0.45};
  s.gravity = Eigen::Vector3d(0.3, -0.8, -0.5);
}
void vertex(SinkingSpec& s) {
  s.craniotomy_direction = {0.15, -0.1, 1.0};
  s.gravity = Eigen::Vector3d(0, 0, -1);
}
void parietal_right(SinkingSpec& s) {
  s.craniotomy_direction = {0.6, -0.5, 0.6};
  s.gravity = Eigen::Vector3d(-0.8, 0.2, -0.55);
}
void temporal_left(SinkingSpec& s) {
  s.craniotomy_direction = {-1.0, 0.1, -0.2};
  s.gravity = Eigen::Vector3d(1, 0, 0);
}
void frontal_right(SinkingSpec& s) { s.craniotomy_direction = {0.55, 0.7, 0.45}; }

void sinking(PhantomSpec& p, double cortex_mm, double deep_mm, double decay_mm) {
  p.sinking.cortex_mm = cortex_mm;
  p.sinking.deep_mm = deep_mm;
  p.sinking.depth_decay_mm = decay_mm;
  p.sinking.lateral_radius_mm = 50;
}

void retractor(PhantomSpec& p, double depth_mm, double angle_deg) {
  p.retractor.enabled = true;
  p.retractor.depth_mm = depth_mm;
  p.retractor.blade_angle_deg = angle_deg;
  p.retractor.half_width_mm = 2.5;
  p.retractor.half_length_mm = 12;
  p.retractor.depth_decay_mm = 12;
}

// The scanners (field strength as resolution, SNR and bias).
ScannerSpec scanner(const std::string& name, const Eigen::Vector3d& spacing_mm, const Eigen::Vector3d& fov_mm,
                    double snr, double bias_amplitude) {
  ScannerSpec s;
  s.name = name;
  s.spacing_mm = spacing_mm;
  s.fov_mm = fov_mm;
  s.snr = snr;
  s.bias_amplitude = bias_amplitude;
  return s;
}
ScannerSpec scanner_1p5t() { return scanner("1.5T_1mm_iso", {1, 1, 1}, {180, 216, 160}, 25, 0.1); }
ScannerSpec scanner_0p5t() { return scanner("0.5T_1.2x1.2x2mm", {1.2, 1.2, 2.0}, {190, 220, 170}, 12, 0.2); }
ScannerSpec scanner_0p15t() { return scanner("0.15T_1.7x1.7x2.4mm", {1.7, 1.7, 2.4}, {200, 230, 175}, 7, 0.4); }
// A short coil over the craniotomy: 120 mm along S-I, centred 20 mm above
// the brain's centroid, so the field of view ends some 35 mm into the
// base (temporal poles, cerebellum); its sensitivity falls off (strong bias).
ScannerSpec short_coil_1p5t() {
  ScannerSpec s = scanner("1.5T_short_coil_1mm_120mmSI", {1, 1, 1}, {180, 216, 120}, 20, 0.3);
  s.fov_centre_offset_mm = {0, 0, 20};
  return s;
}
ScannerSpec sagittal_3mm() {
  // fov: S-I, A-P, then R-L across slices.
  ScannerSpec s = scanner("sagittal_1x1x3mm", {1, 1, 3}, {170, 220, 180}, 18, 0.15);
  s.orientation_deg = sagittal_deg();
  return s;
}
ScannerSpec oblique(ScannerSpec s, const Eigen::Vector3d& deg) {
  s.name += "_oblique" + std::to_string(static_cast<int>(std::lround(deg.norm()))) + "deg";
  s.orientation_deg = deg;
  return s;
}
ScannerSpec t2_like(ScannerSpec s) {
  s.name = "T2like_" + s.name;
  s.contrast = Contrast::t2_like;
  return s;
}

HospitalCaseSpec hospital_case(const std::string& name, std::uint64_t seed, const std::string& subject_name,
                               const ScannerSpec& scanner) {
  HospitalCaseSpec c;
  c.subject = subject_name;
  c.deformation.name = name;
  c.deformation.seed = seed;
  c.scanner = scanner;
  return c;
}

std::size_t count_label(const LabelImage& labels, std::uint16_t l) {
  return static_cast<std::size_t>(std::count(labels.voxels.begin(), labels.voxels.end(), l));
}

// The subject's left and right ventricle centroids (split at their joint
// centroid's x), moved by the rigid head move.
std::vector<Eigen::Vector3d> ventricle_seeds(const LabelImage& preop, std::uint16_t ventricle, const Eigen::Matrix4d& rigid) {
  const Mask vent = mask_of_labels(preop, {ventricle});
  if (count_nonzero(vent) == 0) return {};
  const double mid_x = centroid_mm(vent).x();
  Mask left(vent.grid, 0), right(vent.grid, 0);
  const Grid3& g = vent.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        if (vent.at(i, j, k)) (g.world_mm(i, j, k).x() < mid_x ? left : right).at(i, j, k) = 1;
  std::vector<Eigen::Vector3d> seeds;
  for (const Mask* m : {&left, &right})
    if (count_nonzero(*m) > 0) seeds.push_back((rigid * centroid_mm(*m).homogeneous()).head<3>());
  return seeds;
}

}  // namespace

double label_dice(const LabelImage& a, const LabelImage& b, std::uint16_t l) {
  std::size_t both = 0, na = 0, nb = 0;
  for (std::size_t v = 0; v < a.voxels.size(); ++v) {
    na += a.voxels[v] == l;
    nb += b.voxels[v] == l;
    both += a.voxels[v] == l && b.voxels[v] == l;
  }
  return 2.0 * static_cast<double>(both) / static_cast<double>(std::max<std::size_t>(1, na + nb));
}

std::vector<SubjectSpec> hospital_subjects() {
  std::vector<SubjectSpec> s;
  s.push_back(subject("atlas", 1, {1, 1, 1}, 0, 0, 30));
  s.push_back(subject("small_head", 2, {0.92, 0.95, 0.91}, 5, 4, 30));
  s.push_back(subject("large_head", 3, {1.08, 1.05, 1.10}, 5, 5, 35));
  {
    SubjectSpec e = subject("enlarged_ventricles_x1.8", 4, {1.0, 1.03, 0.97}, 3, 3, 30);
    e.ventricle_volume_factor = 1.8;
    s.push_back(e);
  }
  {
    SubjectSpec h = subject("hydrocephalus_x2.4", 5, {0.95, 1.04, 1.02}, 4, 4, 32);
    h.ventricle_volume_factor = 2.4;
    s.push_back(h);
  }
  {
    SubjectSpec m = subject("tumour_mass_effect", 6, {1.03, 0.97, 1.0}, 3, 3, 30);
    m.mass_effect = MassEffectSpec{};
    s.push_back(m);
  }
  {
    SubjectSpec t = subject("superficial_tumour", 7, {0.96, 1.02, 1.05}, 4, 4, 30);
    TumorImplantSpec tumor;
    tumor.direction = {0.55, 0.7, 0.45};
    tumor.depth_mm = 14;
    tumor.radius_mm = 12;
    tumor.seed = 7;
    t.tumor = tumor;
    s.push_back(t);
  }
  return s;
}

std::vector<HospitalCaseSpec> hospital_suite() {
  std::vector<HospitalCaseSpec> suite;
  {  // The control: the atlas head, ordinary sinking, a good scanner.
    HospitalCaseSpec c = hospital_case("control_atlas_sink9_1.5T", 201, "atlas", scanner_1p5t());
    frontal_left(c.deformation.sinking);
    sinking(c.deformation, 9, 2, 30);
    suite.push_back(c);
  }
  {  // Older patient, vertex craniotomy, large sinking after CSF drainage.
    HospitalCaseSpec c = hospital_case("enlarged_ventricles_sink24_1.5T", 202, "enlarged_ventricles_x1.8", scanner_1p5t());
    vertex(c.deformation.sinking);
    sinking(c.deformation, 24, 5, 35);
    suite.push_back(c);
  }
  {  // Large sinking plus a retractor, at low field.
    HospitalCaseSpec c = hospital_case("large_head_sink25_retractor_0.15T", 203, "large_head", scanner_0p15t());
    parietal_right(c.deformation.sinking);
    sinking(c.deformation, 25, 5, 35);
    retractor(c.deformation, 7, 30);
    c.scene.gap_fluid_fraction = 0.3;
    suite.push_back(c);
  }
  {  // T2-like: a superficial tumour resected, swelling on the other side.
    HospitalCaseSpec c = hospital_case("tumour_resection_swelling_T2", 204, "superficial_tumour", t2_like(scanner_0p5t()));
    frontal_right(c.deformation.sinking);
    sinking(c.deformation, 8, 2, 30);
    c.deformation.resection.enabled = true;
    c.deformation.resection.collapse_mm = 4;
    c.deformation.swelling.enabled = true;
    c.deformation.swelling.amplitude_mm = 3;
    c.deformation.swelling.centre_offset_mm = {-30, 5, 10};
    c.scene.gap_fluid_fraction = 0.8;
    suite.push_back(c);
  }
  {  // Hydrocephalus, sagittal 3 mm slices, a retractor dent.
    HospitalCaseSpec c = hospital_case("hydrocephalus_retractor_sagittal3mm", 205, "hydrocephalus_x2.4", sagittal_3mm());
    frontal_left(c.deformation.sinking);
    sinking(c.deformation, 12, 3, 30);
    retractor(c.deformation, 7, 0);
    suite.push_back(c);
  }
  {  // Mass effect: the ventricle compressed, the midline shifted 5 mm.
    HospitalCaseSpec c = hospital_case("mass_effect_midline5_0.5T", 206, "tumour_mass_effect", scanner_0p5t());
    frontal_left(c.deformation.sinking);
    sinking(c.deformation, 10, 2, 30);
    c.deformation.midline_shift.enabled = true;
    c.deformation.midline_shift.amplitude_mm = 5;
    c.deformation.midline_shift.direction = {1, 0, 0};
    suite.push_back(c);
  }
  {  // Partial resection of a superficial hypointense tumour, blood in the cavity, low field.
    HospitalCaseSpec c = hospital_case("partial_resection_blood_0.15T", 207, "superficial_tumour", scanner_0p15t());
    frontal_right(c.deformation.sinking);
    sinking(c.deformation, 8, 2, 30);
    c.deformation.resection.enabled = true;
    c.deformation.resection.collapse_mm = 3;
    c.deformation.resection.resected_fraction = 0.6;
    c.deformation.resection.blood_fill_fraction = 0.5;
    suite.push_back(c);
  }
  {  // A small head, large sinking, a strongly oblique grid.
    HospitalCaseSpec c = hospital_case("small_head_sink20_oblique28_0.5T", 208, "small_head",
                                       oblique(scanner_0p5t(), {26, 0, 10}));
    temporal_left(c.deformation.sinking);
    sinking(c.deformation, 20, 4, 35);
    suite.push_back(c);
  }
  {  // Midline shift on the atlas head, T2-like on an oblique grid.
    HospitalCaseSpec c = hospital_case("atlas_midline6_T2_oblique25", 209, "atlas",
                                       t2_like(oblique(scanner_1p5t(), {0, 25, 0})));
    c.deformation.name = "atlas_midline6_T2_oblique25";
    frontal_left(c.deformation.sinking);
    sinking(c.deformation, 8, 2, 30);
    c.deformation.midline_shift.enabled = true;
    c.deformation.midline_shift.amplitude_mm = 6;
    c.deformation.midline_shift.direction = {-1, 0, 0};
    suite.push_back(c);
  }
  {  // A large head, 22 mm vertex sinking, sagittal slices.
    HospitalCaseSpec c = hospital_case("large_head_sink22_sagittal3mm", 210, "large_head", sagittal_3mm());
    vertex(c.deformation.sinking);
    sinking(c.deformation, 22, 4, 35);
    suite.push_back(c);
  }
  {  // Enlarged ventricles, a resection without a tumour label, swelling opposite, low field.
    HospitalCaseSpec c = hospital_case("enlarged_ventricles_resection_swelling_0.15T", 211, "enlarged_ventricles_x1.8",
                                       scanner_0p15t());
    parietal_right(c.deformation.sinking);
    sinking(c.deformation, 10, 2, 30);
    c.deformation.resection.enabled = true;
    c.deformation.resection.ball_radius_mm = 10;
    c.deformation.resection.collapse_mm = 4;
    c.deformation.resection.blood_fill_fraction = 0.3;
    c.deformation.swelling.enabled = true;
    c.deformation.swelling.amplitude_mm = 3;
    c.deformation.swelling.centre_offset_mm = {-28, 0, 15};
    suite.push_back(c);
  }
  {  // Hydrocephalus, 20 mm sinking and the head repositioned.
    HospitalCaseSpec c = hospital_case("hydrocephalus_sink20_rigid_1.5T", 212, "hydrocephalus_x2.4", scanner_1p5t());
    frontal_left(c.deformation.sinking);
    sinking(c.deformation, 20, 4, 35);
    c.deformation.rigid.rotation_deg = {4, -3, 3};
    c.deformation.rigid.translation_mm = {3, -2, 4};
    suite.push_back(c);
  }
  {  // The base out of view (a short coil) under a vertex sinking: nothing
     // below holds the brain's affine, the gap above pulls it down.
    HospitalCaseSpec c = hospital_case("mass_effect_vertex_sink22_short_coil_1.5T", 213, "tumour_mass_effect", short_coil_1p5t());
    vertex(c.deformation.sinking);
    sinking(c.deformation, 22, 4, 35);
    suite.push_back(c);
  }
  return suite;
}

HospitalCase make_hospital_case(const Subject& subject, const HospitalCaseSpec& spec) {
  const auto t0 = std::chrono::steady_clock::now();
  PhantomSpec p = spec.deformation;
  apply_scanner_grid(spec.scanner, p);
  p.label_noise_mm = 0;
  p.noise_fraction = 0;
  p.bias_amplitude = 0;
  p.preop_tumor.reset();  // a subject's tumour is in its images already
  HospitalCase out;
  out.phantom = make_phantom(subject.t1, subject.labels, p);
  out.true_labels = out.phantom.intraop_labels;
  PhantomDeformation phi(subject.labels, p);
  phi.scale_nonrigid(out.phantom.description["nonrigid_scale_applied"].get<double>());
  const auto t_truth = std::chrono::steady_clock::now();

  const IntraopScene scene = make_intraop_scene(subject.t1, subject.labels, p, phi, spec.scene);
  std::mt19937_64 rng(p.seed * 2654435761ULL + 11);
  out.phantom.intraop_t1 = acquire(scene, spec.scanner, out.true_labels.grid, rng);
  const auto t_image = std::chrono::steady_clock::now();

  ThresholdSegmenterSpec seg_spec = spec.segmenter;
  seg_spec.contrast = spec.scanner.contrast;
  const auto seeds = ventricle_seeds(subject.labels, p.ventricle_label, phi.intraop_from_preop_rigid());
  // The expected brain and ventricles: the preop's, moved by the rigid head move.
  const LabelImage moved = resample_nearest(subject.labels, out.true_labels.grid, phi.intraop_from_preop_rigid().inverse());
  const Mask expected_brain = mask_of_labels(moved, p.brain_labels);
  const Mask expected_ventricles = mask_of_labels(moved, {p.ventricle_label});
  const ThresholdSegmentation seg =
      segment_by_threshold(out.phantom.intraop_t1, {seeds, &expected_brain, &expected_ventricles}, seg_spec);
  out.phantom.intraop_labels = seg.labels;
  const auto t_end = std::chrono::steady_clock::now();

  Mask seg_brain(seg.labels.grid, 0), true_brain(seg.labels.grid, 0);
  for (std::size_t v = 0; v < seg_brain.voxels.size(); ++v) {
    seg_brain.voxels[v] = seg.labels.voxels[v] != 0;
    true_brain.voxels[v] = out.true_labels.voxels[v] != 0;
  }
  LabelImage a(seg.labels.grid, 0), b(seg.labels.grid, 0);
  for (std::size_t v = 0; v < a.voxels.size(); ++v) a.voxels[v] = seg_brain.voxels[v], b.voxels[v] = true_brain.voxels[v];
  const double voxel_ml = std::abs(seg.labels.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
  auto secs = [](auto x, auto y) { return std::chrono::duration<double>(y - x).count(); };
  nlohmann::json d = out.phantom.description;
  d["subject"] = subject.name;
  d["scanner"] = to_json(spec.scanner);
  d["scene"] = {{"gap_fluid_fraction", spec.scene.gap_fluid_fraction}, {"csf_rim_mm", spec.scene.csf_rim_mm}};
  d["segmentation"] = seg.description;
  d["segmentation"]["against_truth"] = {
      {"brain_dice", label_dice(a, b, 1)},
      {"ventricle_dice", label_dice(seg.labels, out.true_labels, seg_spec.ventricle_label)},
      {"brain_volume_ratio", static_cast<double>(count_nonzero(seg_brain)) / std::max<std::size_t>(1, count_nonzero(true_brain))},
      {"true_ventricles_ml", count_label(out.true_labels, seg_spec.ventricle_label) * voxel_ml}};
  d["seconds"]["truth"] = secs(t0, t_truth);
  d["seconds"]["scanner"] = secs(t_truth, t_image);
  d["seconds"]["segmenter"] = secs(t_image, t_end);
  out.description = std::move(d);
  out.phantom.description = out.description;
  return out;
}

}  // namespace brainshift
