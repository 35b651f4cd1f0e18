#include "phantom/brain_shift_phantom.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <limits>
#include <cmath>
#include <random>
#include <thread>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "image/resample.h"
#include "phantom/random_fields.h"

namespace brainshift {
namespace {

constexpr double kPi = 3.14159265358979323846;

Eigen::Matrix3d rotation_deg(const Eigen::Vector3d& deg) {
  const Eigen::Vector3d r = deg * kPi / 180.0;
  return (Eigen::AngleAxisd(r.z(), Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(r.y(), Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(r.x(), Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

std::array<bool, 65536> label_set(const std::vector<std::uint16_t>& labels) {
  std::array<bool, 65536> s{};
  for (auto l : labels) s[l] = true;
  return s;
}

// Runs fn(k) for every slice k on two threads (the target machines have 2 cores).
template <class F>
void parallel_slices(int nk, F&& fn) {
  const int threads = std::max(1u, std::min(2u, std::thread::hardware_concurrency()));
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t)
    pool.emplace_back([&, t] {
      for (int k = t; k < nk; k += threads) fn(k);
    });
  for (auto& th : pool) th.join();
}

Eigen::Vector3d mask_centroid(const LabelImage& labels, const std::array<bool, 65536>& in) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  std::size_t n = 0;
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (in[labels.at(i, j, k)]) {
          sum += Eigen::Vector3d(i, j, k);
          ++n;
        }
  if (n == 0) return Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  const Eigen::Vector3d v = sum / static_cast<double>(n);
  return labels.grid.world_mm(v.x(), v.y(), v.z());
}

std::size_t count_label(const LabelImage& labels, std::uint16_t l) {
  return static_cast<std::size_t>(std::count(labels.voxels.begin(), labels.voxels.end(), l));
}

void check_spec(const PhantomSpec& s) {
  auto fail = [&](const std::string& what) { throw InputError("phantom '" + s.name + "': " + what); };
  if (s.dims[0] < 2 || s.dims[1] < 2 || s.dims[2] < 2) fail("intraop grid dims must be >= 2");
  if (!(s.spacing_mm.minCoeff() > 0.05 && s.spacing_mm.maxCoeff() < 20)) fail("intraop spacing must be in (0.05, 20) mm");
  const auto& k = s.sinking;
  if (k.enabled && !(k.cortex_mm >= 0 && k.cortex_mm <= 40 && k.deep_mm >= 0 && k.deep_mm <= k.cortex_mm &&
                     k.depth_decay_mm > 0 && k.lateral_radius_mm > 0 && k.craniotomy_direction.norm() > 0))
    fail("sinking needs 0 <= deep_mm <= cortex_mm <= 40, positive decay and radius, a non-zero direction");
  if (s.swelling.enabled && !(s.swelling.amplitude_mm >= 0 && s.swelling.radius_mm > 0))
    fail("swelling needs amplitude_mm >= 0 and radius_mm > 0");
  const auto& r = s.resection;
  if (r.enabled && !(r.ball_radius_mm > 0 && r.collapse_mm >= 0 && r.collapse_decay_mm > 0))
    fail("resection needs ball_radius_mm > 0, collapse_mm >= 0, collapse_decay_mm > 0");
  if (!(s.bias_amplitude >= 0 && s.bias_amplitude < 1 && s.noise_fraction >= 0 && s.label_noise_mm >= 0 &&
        s.label_noise_correlation_mm > 0 && s.min_jacobian > 0 && s.min_jacobian < 1))
    fail("bias in [0,1), noise >= 0, correlation > 0 and min_jacobian in (0,1) are required");
}

}  // namespace

// ---------------------------------------------------------------------------
// The analytic deformation.

PhantomDeformation::PhantomDeformation(const LabelImage& labels, const PhantomSpec& spec) : spec_(spec) {
  check_spec(spec);
  if (labels.grid.voxel_count() == 0 || labels.voxels.size() != labels.grid.voxel_count())
    throw InputError("phantom '" + spec.name + "': the preop label image is empty");
  const auto brain = label_set(spec.brain_labels);
  centroid_ = mask_centroid(labels, brain);
  if (!centroid_.allFinite()) throw InputError("phantom '" + spec.name + "': no brain label in the preop labels");
  const GridSampler sampler(labels.grid);

  const auto& sk = spec.sinking;
  const Eigen::Vector3d outward = sk.craniotomy_direction.normalized();
  // The craniotomy is the last brain point along the ray (skipping sulci).
  bool found = false;
  for (double t = 0; t <= 200; t += 0.5) {
    const Eigen::Vector3d p = centroid_ + t * outward;
    if (brain[sampler.nearest(labels.voxels, p, 0)]) {
      craniotomy_ = p;
      found = t > 0;
    }
  }
  if (sk.enabled && !found)
    throw InputError("phantom '" + spec.name + "': the craniotomy ray from the brain centroid finds no cortex");
  gravity_ = sk.gravity ? sk.gravity->normalized() : Eigen::Vector3d(-outward);
  if (sk.enabled && gravity_.dot(-outward) < 0.3)
    throw InputError("phantom '" + spec.name + "': gravity must point into the brain at the craniotomy");
  // Extent of the brain along gravity from the craniotomy (last brain point on that line).
  brain_depth_mm_ = 0;
  for (double t = 0; t <= 250; t += 0.5)
    if (brain[sampler.nearest(labels.voxels, craniotomy_ + t * gravity_, 0)]) brain_depth_mm_ = t;
  brain_depth_mm_ = std::max(brain_depth_mm_, 20.0);

  swelling_centre_ = centroid_ + spec.swelling.centre_offset_mm;

  const auto& rs = spec.resection;
  if (rs.enabled) {
    const std::size_t tumor_voxels = count_label(labels, rs.tumor_label);
    if (tumor_voxels > 0) {
      resection_uses_label_ = true;
      std::array<bool, 65536> t{};
      t[rs.tumor_label] = true;
      resection_centre_ = mask_centroid(labels, t);
      const double volume = tumor_voxels * std::abs(labels.grid.world_from_voxel.topLeftCorner<3, 3>().determinant());
      resection_radius_ = std::cbrt(3 * volume / (4 * kPi));
    } else {
      resection_centre_ = sk.enabled ? Eigen::Vector3d(craniotomy_ + rs.ball_depth_mm * gravity_)
                                     : Eigen::Vector3d(centroid_ + rs.centre_offset_mm);
      resection_radius_ = rs.ball_radius_mm;
    }
    if (rs.collapse_mm >= 0.8 * resection_radius_)
      throw InputError("phantom '" + spec.name + "': collapse_mm must be below 0.8 x the cavity radius (" +
                       std::to_string(resection_radius_) + " mm)");
  }

  rigid_.topLeftCorner<3, 3>() = rotation_deg(spec.rigid.rotation_deg);
  rigid_.topRightCorner<3, 1>() = centroid_ + spec.rigid.translation_mm - rigid_.topLeftCorner<3, 3>() * centroid_;
  rigid_inverse_ = rigid_.inverse();
}

void PhantomDeformation::scale_nonrigid(double factor) { scale_ *= factor; }

// Sinking along gravity: full amplitude at and above the craniotomy depth,
// decaying (Gaussian) with depth to deep_mm, and fading (Gaussian) with the
// distance from the gravity axis through the craniotomy. |grad f| < 1 for the
// validated ranges, so p -> p + f(p) is invertible.
Eigen::Vector3d PhantomDeformation::sink(const Eigen::Vector3d& p) const {
  const auto& s = spec_.sinking;
  if (!s.enabled) return Eigen::Vector3d::Zero();
  const Eigen::Vector3d r = p - craniotomy_;
  const double along = r.dot(gravity_);
  const double depth = std::max(0.0, along);
  const double lateral2 = (r - along * gravity_).squaredNorm();
  const double z = depth / s.depth_decay_mm;
  // The far side rests on the skull: the deep part tapers off over the far
  // half of the brain's extent along gravity.
  const double far = std::clamp((depth - 0.5 * brain_depth_mm_) / (0.5 * brain_depth_mm_), 0.0, 1.0);
  const double taper = 1.0 - far * far * (3.0 - 2.0 * far);
  const double amplitude = s.deep_mm * taper + (s.cortex_mm - s.deep_mm) * std::exp(-z * z);
  return scale_ * amplitude * std::exp(-0.5 * lateral2 / (s.lateral_radius_mm * s.lateral_radius_mm)) * gravity_;
}

// Radial expansion peaking (amplitude_mm) at radius_mm, smooth at the centre.
Eigen::Vector3d PhantomDeformation::swell(const Eigen::Vector3d& p) const {
  const auto& s = spec_.swelling;
  if (!s.enabled) return Eigen::Vector3d::Zero();
  const Eigen::Vector3d r = p - swelling_centre_;
  const double q = r.squaredNorm() / (s.radius_mm * s.radius_mm);
  return scale_ * s.amplitude_mm / s.radius_mm * std::exp(0.5 - 0.5 * q) * r;
}

// Inward radial collapse: the cavity wall moves in by collapse_mm and the
// tissue around it follows, less the farther it is (Gaussian decay with the
// distance from the wall): the wall, which lost its support, moves most.
// Inside the cavity (no tissue, only its image) the contraction is uniform.
// (An earlier form scaled the decay by r/R, so tissue 7 mm out moved 30 %
// more than the wall itself: a compression toward the cavity no loss of
// support produces.)
Eigen::Vector3d PhantomDeformation::collapse(const Eigen::Vector3d& p) const {
  if (!spec_.resection.enabled) return Eigen::Vector3d::Zero();
  const Eigen::Vector3d r = p - resection_centre_;
  const double n = r.norm();
  const double amplitude = scale_ * spec_.resection.collapse_mm;
  if (n <= resection_radius_) return -amplitude / resection_radius_ * r;
  const double beyond = (n - resection_radius_) / spec_.resection.collapse_decay_mm;
  return -amplitude * std::exp(-beyond * beyond) / n * r;
}

template <class F>
Eigen::Vector3d PhantomDeformation::invert_component(const Eigen::Vector3d& y, F&& f) {
  // Solve p + f(p) = y by fixed-point iteration: a contraction since |grad f| < 1.
  Eigen::Vector3d p = y - f(y);
  for (int it = 0; it < 200; ++it) {
    const Eigen::Vector3d next = y - f(p);
    const double change = (next - p).squaredNorm();
    p = next;
    if (change < 1e-12) break;
  }
  return p;
}

Eigen::Vector3d PhantomDeformation::forward(const Eigen::Vector3d& preop_mm) const {
  Eigen::Vector3d p = preop_mm + sink(preop_mm);
  p += swell(p);
  p += collapse(p);
  return (rigid_ * p.homogeneous()).head<3>();
}

Eigen::Vector3d PhantomDeformation::inverse(const Eigen::Vector3d& intraop_mm) const {
  Eigen::Vector3d y = (rigid_inverse_ * intraop_mm.homogeneous()).head<3>();
  if (spec_.resection.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return collapse(q); });
  if (spec_.swelling.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return swell(q); });
  if (spec_.sinking.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return sink(q); });
  return y;
}

double min_jacobian_determinant(const VectorImage3& u) {
  const Grid3& g = u.grid;
  const Eigen::Matrix3d voxel_from_world_linear = g.world_from_voxel.topLeftCorner<3, 3>().inverse();
  const auto& d = g.dims;
  std::vector<double> slice_min(d[2], std::numeric_limits<double>::max());
  parallel_slices(d[2], [&](int k) {
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        // Derivatives along the voxel axes, then chain rule to world axes.
        Eigen::Matrix3d du_dvoxel;
        const int idx[3] = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          int lo[3] = {i, j, k}, hi[3] = {i, j, k};
          lo[a] = std::max(0, idx[a] - 1);
          hi[a] = std::min(d[a] - 1, idx[a] + 1);
          if (hi[a] == lo[a]) {
            du_dvoxel.col(a).setZero();
            continue;
          }
          du_dvoxel.col(a) = (u.vectors[g.index(hi[0], hi[1], hi[2])] - u.vectors[g.index(lo[0], lo[1], lo[2])])
                                 .cast<double>() /
                             (hi[a] - lo[a]);
        }
        const double det = (Eigen::Matrix3d::Identity() + du_dvoxel * voxel_from_world_linear).determinant();
        slice_min[k] = std::min(slice_min[k], det);
      }
  });
  return *std::min_element(slice_min.begin(), slice_min.end());
}

// ---------------------------------------------------------------------------
// The images.
namespace {

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
  if (values.empty()) return 0;
  const std::size_t n = std::min(values.size() - 1, static_cast<std::size_t>(q * (values.size() - 1)));
  std::nth_element(values.begin(), values.begin() + n, values.end());
  return values[n];
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
  const Grid3 grid = intraop_grid(spec, (phi.intraop_from_preop_rigid() * phi.brain_centroid_mm().homogeneous()).head<3>());

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
    if (phi.resection_uses_tumor_label()) return sdt.linear(maps.sd_tumor.voxels, p, 1e3f);
    return (p - phi.resection_centre_mm()).norm() - phi.resection_radius_mm();
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
  // Rician noise (sequential: one random stream, deterministic).
  if (sigma > 0) {
    std::normal_distribution<double> normal(0, sigma);
    for (auto& val : out.intraop_t1.voxels) {
      const double re = val + normal(rng), im = normal(rng);
      val = static_cast<float>(std::sqrt(re * re + im * im));
    }
  }
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
  d["rigid"] = {{"rotation_deg", vec(spec.rigid.rotation_deg)}, {"translation_mm", vec(spec.rigid.translation_mm)}};
  d["grid"] = {{"dims", spec.dims}, {"spacing_mm", vec(spec.spacing_mm)}, {"oblique_deg", vec(spec.oblique_deg)},
               {"flip_first_axis", spec.flip_first_axis}};
  d["noise"] = {{"bias_amplitude", spec.bias_amplitude}, {"rician_sigma", sigma},
                {"label_noise_mm", spec.label_noise_mm}, {"label_noise_correlation_mm", spec.label_noise_correlation_mm}};
  d["landmarks"] = out.landmarks_intraop_preop_mm.size();
  d["seconds"] = {{"field", secs(t_start, t_field)}, {"images", secs(t_field, t_images)}, {"landmarks", secs(t_images, t_end)}};
  out.description = std::move(d);
  return out;
}

std::vector<PhantomSpec> standard_phantom_suite() {
  std::vector<PhantomSpec> suite;
  auto base = [](const std::string& name, std::uint64_t seed) {
    PhantomSpec s;
    s.name = name;
    s.seed = seed;
    return s;
  };
  {  // Supine, frontal craniotomy: the classic case.
    PhantomSpec s = base("left_frontal_sinking_12mm", 11);
    s.sinking.craniotomy_direction = {-0.5, 0.75, 0.45};
    s.sinking.gravity = Eigen::Vector3d(0.3, -0.8, -0.5);
    s.sinking.cortex_mm = 12;
    s.sinking.deep_mm = 2;
    suite.push_back(s);
  }
  {  // Lateral position, large shift after CSF drainage.
    PhantomSpec s = base("right_parietal_sinking_18mm", 12);
    s.sinking.craniotomy_direction = {0.6, -0.5, 0.6};
    s.sinking.gravity = Eigen::Vector3d(-0.8, 0.2, -0.55);
    s.sinking.cortex_mm = 18;
    s.sinking.deep_mm = 3;
    s.sinking.depth_decay_mm = 35;
    s.sinking.lateral_radius_mm = 50;
    suite.push_back(s);
  }
  {  // Prone, small shift, and the head was repositioned.
    PhantomSpec s = base("occipital_sinking_6mm_rigid", 13);
    s.sinking.craniotomy_direction = {0.1, -1.0, 0.2};
    s.sinking.gravity = Eigen::Vector3d(0, 1, 0);
    s.sinking.cortex_mm = 6;
    s.sinking.deep_mm = 1;
    s.rigid.rotation_deg = {3, -2, 4};
    s.rigid.translation_mm = {2, -3, 1.5};
    suite.push_back(s);
  }
  {  // Oedema without an opening, oblique acquisition.
    PhantomSpec s = base("deep_swelling_4mm_oblique", 14);
    s.sinking.enabled = false;
    s.swelling.enabled = true;
    s.swelling.amplitude_mm = 4;
    s.swelling.radius_mm = 25;
    s.swelling.centre_offset_mm = {-25, 10, 15};
    s.rigid.rotation_deg = {-2, 1, 0};
    s.oblique_deg = {12, 0, 8};
    suite.push_back(s);
  }
  {  // A right frontal tumor (12 mm, lobulated) resected under the
     // craniotomy; the cavity collapses.
    PhantomSpec s = base("right_frontal_tumor_resection", 15);
    s.sinking.craniotomy_direction = {0.55, 0.7, 0.45};
    s.sinking.cortex_mm = 8;
    s.sinking.deep_mm = 2;
    TumorImplantSpec tumor;
    tumor.direction = s.sinking.craniotomy_direction;
    tumor.depth_mm = 18;
    tumor.radius_mm = 12;
    tumor.seed = 15;
    s.preop_tumor = tumor;
    s.resection.enabled = true;
    s.resection.collapse_mm = 5;
    suite.push_back(s);
  }
  {  // Lateral decubitus, left temporal; everything at once, noisy, flipped oblique grid.
    PhantomSpec s = base("left_temporal_mixed_noisy", 16);
    s.sinking.craniotomy_direction = {-1.0, 0.1, -0.2};
    s.sinking.gravity = Eigen::Vector3d(1, 0, 0);
    s.sinking.cortex_mm = 15;
    s.sinking.deep_mm = 4;
    s.swelling.enabled = true;
    s.swelling.amplitude_mm = 2;
    s.swelling.centre_offset_mm = {-30, 0, 0};
    s.rigid.rotation_deg = {-4, 3, -2};
    s.rigid.translation_mm = {-3, 2, -2};
    s.oblique_deg = {-10, 6, 0};
    s.flip_first_axis = true;
    s.noise_fraction = 0.06;
    s.bias_amplitude = 0.25;
    s.label_noise_mm = 1.5;
    suite.push_back(s);
  }
  {  // Vertex craniotomy, supine head up: the largest sinking.
    PhantomSpec s = base("vertex_sinking_20mm", 17);
    s.sinking.craniotomy_direction = {0.15, -0.1, 1.0};
    s.sinking.gravity = Eigen::Vector3d(0, 0, -1);
    s.sinking.cortex_mm = 20;
    s.sinking.deep_mm = 5;
    s.sinking.depth_decay_mm = 40;
    s.sinking.lateral_radius_mm = 55;
    suite.push_back(s);
  }
  return suite;
}

}  // namespace brainshift
