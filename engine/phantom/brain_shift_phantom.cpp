// The phantom's images (brain_shift_phantom.h: make_phantom): the intraop T1,
// labels, landmarks and description from the analytic deformation
// (phantom_deformation.cpp) and the artefacts (phantom_artefacts.h).
#include "phantom/brain_shift_phantom.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <random>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "image/resample.h"
#include "phantom/phantom_artefacts.h"
#include "phantom/phantom_support.h"

namespace brainshift {
namespace {

using namespace phantom_detail;

Grid3 intraop_grid(const PhantomSpec& s, const Eigen::Vector3d& centre_mm) {
  Grid3 g;
  g.dims = s.dims;
  Eigen::Matrix3d axes = rotation_deg(s.oblique_deg);
  if (s.flip_first_axis) axes.col(0) *= -1;
  const Eigen::Matrix3d linear = axes * s.spacing_mm.asDiagonal();
  g.world_from_voxel.topLeftCorner<3, 3>() = linear;
  const Eigen::Vector3d mid((s.dims[0] - 1) / 2.0, (s.dims[1] - 1) / 2.0, (s.dims[2] - 1) / 2.0);
  g.world_from_voxel.topRightCorner<3, 1>() = centre_mm - linear * mid;
  return g;
}

double percentile_in(const ImageF& t1, const LabelImage& labels, const std::array<bool, 65536>& in, double q) {
  std::vector<float> values;
  const GridSampler ls(labels.grid);
  const bool same = t1.grid.same_geometry(labels.grid);
  for (int k = 0; k < t1.grid.dims[2]; ++k)
    for (int j = 0; j < t1.grid.dims[1]; ++j)
      for (int i = 0; i < t1.grid.dims[0]; ++i) {
        const std::size_t idx = t1.grid.index(i, j, k);
        const std::uint16_t l = same ? labels.voxels[idx] : ls.nearest(labels.voxels, t1.grid.world_mm(i, j, k), 0);
        if (in[l]) values.push_back(t1.voxels[idx]);
      }
  return quantile(std::move(values), q);  // the same order statistic as every phantom quantile
}

// Signed distance (mm, negative inside) of the preop voxels with these labels.
ImageF signed_distance_of(const LabelImage& labels, const std::vector<std::uint16_t>& which) {
  return signed_distance_mm(mask_of_labels(labels, which));
}

VectorImage3 pullback_field(const PhantomDeformation& phi, const Grid3& g) {
  VectorImage3 u(g);
  parallel_slices(g.dims[2], [&](int k) {
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        u.vectors[g.index(i, j, k)] = (phi.inverse(x) - x).cast<float>();
      }
  });
  return u;
}

struct PreopMaps {
  ImageF sd_brain, sd_ventricles, sd_tumor;
};

}  // namespace

PhantomCase make_phantom(const ImageF& preop_t1, const LabelImage& preop_labels, const PhantomSpec& spec) {
  const auto t_start = std::chrono::steady_clock::now();
  if (preop_t1.grid.voxel_count() == 0 || preop_t1.voxels.size() != preop_t1.grid.voxel_count())
    throw InputError("phantom '" + spec.name + "': the preop T1 is empty");
  PhantomDeformation phi(preop_labels, spec);
  const auto brain_set = label_set(spec.brain_labels);
  PhantomCase out;
  out.true_intraop_from_preop_rigid = phi.intraop_from_preop_rigid();
  const Grid3 grid = intraop_grid(
      spec, (phi.intraop_from_preop_rigid() * phi.brain_centroid_mm().homogeneous()).head<3>() + spec.grid_centre_offset_mm);

  // The truth, scaled down until the pull-back is comfortably invertible.
  double min_jac = 0;
  for (int attempt = 0;; ++attempt) {
    out.true_pullback_mm = pullback_field(phi, grid);
    min_jac = min_jacobian_determinant(out.true_pullback_mm);
    if (min_jac > spec.min_jacobian) break;
    if (attempt == 12) throw ComputeError("phantom '" + spec.name + "': cannot keep the Jacobian above min_jacobian");
    phi.scale_nonrigid(0.8);
  }
  const auto t_field = std::chrono::steady_clock::now();

  PreopMaps maps;
  maps.sd_brain = signed_distance_of(preop_labels, spec.brain_labels);
  maps.sd_ventricles = signed_distance_of(preop_labels, {spec.ventricle_label});
  const bool resect = spec.resection.enabled;
  if (resect && phi.resection_uses_tumor_label()) maps.sd_tumor = signed_distance_of(preop_labels, {spec.resection.tumor_label});

  std::mt19937_64 rng(spec.seed);
  const auto noise_brain = smooth_noise(grid, spec.label_noise_correlation_mm, spec.label_noise_mm, rng);
  const auto noise_vent = smooth_noise(grid, spec.label_noise_correlation_mm, spec.label_noise_mm, rng);
  const auto noise_cavity = smooth_noise(grid, spec.label_noise_correlation_mm, spec.label_noise_mm, rng);
  const auto bias = bias_field(grid, spec.bias_amplitude, rng);

  std::array<bool, 65536> vent_set{};
  vent_set[spec.ventricle_label] = true;
  const double brain_p99 = percentile_in(preop_t1, preop_labels, brain_set, 0.99);
  double fluid = percentile_in(preop_t1, preop_labels, vent_set, 0.5);
  if (fluid <= 0) fluid = 0.1 * brain_p99;  // no ventricles: a dark fluid anyway
  const double sigma = spec.noise_fraction * brain_p99;

  const GridSampler t1s(preop_t1.grid), labs(preop_labels.grid);
  out.intraop_t1 = ImageF(grid, 0.f);
  out.intraop_labels = LabelImage(grid, 0);
  // Noise-free resection/brain membership, reused for landmarks.
  std::vector<std::uint8_t> tissue(grid.voxel_count(), 0);
  const Eigen::Matrix4d preop_from_intraop_rigid = phi.intraop_from_preop_rigid().inverse();
  const GridSampler sdt(phi.resection_uses_tumor_label() ? maps.sd_tumor.grid : grid);
  auto cavity_distance = [&](const Eigen::Vector3d& p) -> double {
    if (!resect) return 1e9;
    const double region = phi.resection_uses_tumor_label() ? sdt.linear(maps.sd_tumor.voxels, p, 1e3f)
                                                           : (p - phi.resection_centre_mm()).norm() - phi.resection_radius_mm();
    return std::max(region, phi.resection_cut_mm(p));
  };
  const GridSampler sdb(maps.sd_brain.grid), sdv(maps.sd_ventricles.grid);
  parallel_slices(grid.dims[2], [&](int k) {
    for (int j = 0; j < grid.dims[1]; ++j)
      for (int i = 0; i < grid.dims[0]; ++i) {
        const std::size_t v = grid.index(i, j, k);
        const Eigen::Vector3d x = grid.world_mm(i, j, k);
        const Eigen::Vector3d p = x + out.true_pullback_mm.vectors[v].cast<double>();
        const double d_brain = sdb.linear(maps.sd_brain.voxels, p, 1e3f);
        const double d_cavity = cavity_distance(p);
        const bool in_brain = d_brain < 0 && d_cavity >= 0;
        tissue[v] = in_brain;
        // Labels: thresholds of distances perturbed by correlated noise.
        std::uint16_t label = 0;
        if (d_brain + noise_brain[v] < 0 && d_cavity + noise_cavity[v] >= 0)
          label = sdv.linear(maps.sd_ventricles.voxels, p, 1e3f) + noise_vent[v] < 0 ? 2 : 1;
        out.intraop_labels.voxels[v] = label;
        // Intensity: brain follows the deformation, the rest only the rigid move.
        double value;
        if (in_brain) {
          value = t1s.linear(preop_t1.voxels, p, 0.f);
        } else if (d_brain < 0) {
          value = fluid;  // resection cavity
        } else {
          // Where the brain was before it moved (same test as in_brain, so a
          // pure rigid move leaves no fluid rim): the gap it left.
          const Eigen::Vector3d q = (preop_from_intraop_rigid * x.homogeneous()).head<3>();
          value = sdb.linear(maps.sd_brain.voxels, q, 1e3f) < 0 ? fluid : t1s.linear(preop_t1.voxels, q, 0.f);
        }
        out.intraop_t1.voxels[v] = static_cast<float>(value * bias[v]);
      }
  });
  if (sigma > 0) add_rician_noise(out.intraop_t1.voxels, sigma, rng);
  const auto t_images = std::chrono::steady_clock::now();

  // Landmarks: tissue voxels, weighted toward the cortex under the
  // craniotomy, the ventricle walls and the tract; jittered within the voxel;
  // the preop point is the exact analytic inverse.
  std::vector<std::size_t> candidates;
  std::vector<double> weights;
  std::array<bool, 65536> tract_set{};
  tract_set[spec.tract_label] = true;
  const double near_craniotomy_mm = 30;
  for (int k = 0; k < grid.dims[2]; ++k)
    for (int j = 0; j < grid.dims[1]; ++j)
      for (int i = 0; i < grid.dims[0]; ++i) {
        const std::size_t v = grid.index(i, j, k);
        if (!tissue[v]) continue;
        const Eigen::Vector3d p = grid.world_mm(i, j, k) + out.true_pullback_mm.vectors[v].cast<double>();
        double w = 1;
        const double d_brain = sdb.linear(maps.sd_brain.voxels, p, 1e3f);
        if (spec.sinking.enabled && (p - phi.craniotomy_mm()).norm() < near_craniotomy_mm && d_brain > -15) w += 6;
        if (std::abs(sdv.linear(maps.sd_ventricles.voxels, p, 1e3f)) < 4) w += 4;
        if (tract_set[labs.nearest(preop_labels.voxels, p, 0)]) w += 4;
        candidates.push_back(v);
        weights.push_back(w);
      }
  if (!candidates.empty()) {
    std::discrete_distribution<std::size_t> pick(weights.begin(), weights.end());
    std::uniform_real_distribution<double> jitter(-0.5, 0.5);
    std::vector<std::uint8_t> used(candidates.size(), 0);
    for (std::size_t tries = 0; out.landmarks_intraop_preop_mm.size() < spec.landmark_count && tries < 50 * spec.landmark_count; ++tries) {
      const std::size_t c = pick(rng);
      if (used[c]) continue;
      used[c] = 1;
      const std::size_t v = candidates[c];
      const int i = static_cast<int>(v % grid.dims[0]), j = static_cast<int>((v / grid.dims[0]) % grid.dims[1]),
                k = static_cast<int>(v / (static_cast<std::size_t>(grid.dims[0]) * grid.dims[1]));
      const Eigen::Vector3d x = grid.world_mm(i + jitter(rng), j + jitter(rng), k + jitter(rng));
      const Eigen::Vector3d p = phi.inverse(x);
      // Well inside the brain (1 mm), where the preop label is unambiguous.
      if (sdb.linear(maps.sd_brain.voxels, p, 1e3f) > -1 || cavity_distance(p) < 1 ||
          !brain_set[labs.nearest(preop_labels.voxels, p, 0)])
        continue;
      out.landmarks_intraop_preop_mm.emplace_back(x, p);
    }
  }
  const auto t_end = std::chrono::steady_clock::now();

  // Description: enough to reproduce and to interpret the case.
  auto vec = [](const Eigen::Vector3d& v) { return nlohmann::json::array({v.x(), v.y(), v.z()}); };
  auto secs = [](auto a, auto b) { return std::chrono::duration<double>(b - a).count(); };
  nlohmann::json d;
  d["name"] = spec.name;
  d["seed"] = spec.seed;
  d["convention"] = "true_pullback_mm: u(x) with x + u(x) = preop point; world RAS+ mm";
  d["brain_centroid_preop_mm"] = vec(phi.brain_centroid_mm());
  d["nonrigid_scale_applied"] = phi.nonrigid_scale();
  d["min_jacobian"] = min_jac;
  Eigen::Matrix4d m = phi.intraop_from_preop_rigid();
  d["intraop_from_preop_rigid"] = nlohmann::json::array();
  for (int r = 0; r < 4; ++r) d["intraop_from_preop_rigid"].push_back({m(r, 0), m(r, 1), m(r, 2), m(r, 3)});
  if (spec.sinking.enabled) {
    const Eigen::Vector3d c = phi.craniotomy_mm();
    d["sinking"] = {{"craniotomy_preop_mm", vec(c)},
                    {"gravity", vec(phi.gravity())},
                    {"cortex_mm", spec.sinking.cortex_mm * phi.nonrigid_scale()},
                    {"deep_mm", spec.sinking.deep_mm * phi.nonrigid_scale()},
                    {"depth_decay_mm", spec.sinking.depth_decay_mm},
                    {"lateral_radius_mm", spec.sinking.lateral_radius_mm},
                    {"craniotomy_displacement_mm", (phi.forward(c) - (m * c.homogeneous()).head<3>()).norm()}};
  }
  if (spec.swelling.enabled)
    d["swelling"] = {{"centre_preop_mm", vec(phi.brain_centroid_mm() + spec.swelling.centre_offset_mm)},
                     {"amplitude_mm", spec.swelling.amplitude_mm * phi.nonrigid_scale()},
                     {"radius_mm", spec.swelling.radius_mm}};
  if (resect)
    d["resection"] = {{"centre_preop_mm", vec(phi.resection_centre_mm())},
                      {"radius_mm", phi.resection_radius_mm()},
                      {"from_tumor_label", phi.resection_uses_tumor_label()},
                      {"collapse_mm", spec.resection.collapse_mm * phi.nonrigid_scale()}};
  if (spec.retractor.enabled)
    d["retractor"] = {{"blade_centre_preop_mm", vec(phi.retractor_centre_mm())},
                      {"depth_mm", spec.retractor.depth_mm * phi.nonrigid_scale()},
                      {"half_length_mm", spec.retractor.half_length_mm},
                      {"half_width_mm", spec.retractor.half_width_mm}};
  if (spec.midline_shift.enabled)
    d["midline_shift"] = {{"centre_preop_mm", vec(phi.brain_centroid_mm() + spec.midline_shift.centre_offset_mm)},
                          {"amplitude_mm", spec.midline_shift.amplitude_mm * phi.nonrigid_scale()},
                          {"radius_mm", spec.midline_shift.radius_mm}};
  if (resect) {
    d["resection"]["resected_fraction"] = spec.resection.resected_fraction;
    d["resection"]["blood_fill_fraction"] = spec.resection.blood_fill_fraction;
  }
  d["rigid"] = {{"rotation_deg", vec(spec.rigid.rotation_deg)}, {"translation_mm", vec(spec.rigid.translation_mm)}};
  d["grid"] = {{"dims", spec.dims}, {"spacing_mm", vec(spec.spacing_mm)}, {"centre_offset_mm", vec(spec.grid_centre_offset_mm)}, {"oblique_deg", vec(spec.oblique_deg)},
               {"flip_first_axis", spec.flip_first_axis}};
  d["noise"] = {{"bias_amplitude", spec.bias_amplitude}, {"rician_sigma", sigma},
                {"label_noise_mm", spec.label_noise_mm}, {"label_noise_correlation_mm", spec.label_noise_correlation_mm}};
  d["landmarks"] = out.landmarks_intraop_preop_mm.size();
  d["seconds"] = {{"field", secs(t_start, t_field)}, {"images", secs(t_field, t_images)}, {"landmarks", secs(t_images, t_end)}};
  out.description = std::move(d);
  return out;
}

}  // namespace brainshift
