// The phantom's analytic deformation (brain_shift_phantom.h: PhantomDeformation)
// and the Jacobian check of its pull-back field.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>

#include "core/errors.h"
#include "core/smoothstep.h"
#include "image/resample.h"
#include "phantom/brain_shift_phantom.h"
#include "phantom/phantom_support.h"

namespace brainshift {
namespace {

using namespace phantom_detail;

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
  if (r.enabled && !(r.resected_fraction > 0 && r.resected_fraction <= 1 && r.blood_fill_fraction >= 0 &&
                     r.blood_fill_fraction <= 1 && r.blood_t1_relative > 0))
    fail("resection needs resected_fraction in (0,1], blood_fill_fraction in [0,1], blood_t1_relative > 0");
  const auto& t = s.retractor;
  if (t.enabled && !(t.depth_mm >= 0 && t.depth_mm <= 20 && t.half_length_mm >= 0 && t.half_width_mm > 0.5 &&
                     t.depth_decay_mm > 0 && 0.86 * t.depth_mm < 0.9 * t.depth_decay_mm &&
                     (!t.push || t.push->norm() > 0)))
    fail("retractor needs depth in [0,20] mm, half width > 0.5 mm, and depth_decay_mm > 0.96 x depth_mm "
         "(the dent must stay invertible along its push)");
  const auto& m = s.midline_shift;
  if (m.enabled && !(m.amplitude_mm >= 0 && m.radius_mm > 0 && 0.61 * m.amplitude_mm < 0.9 * m.radius_mm &&
                     m.direction.norm() > 0))
    fail("midline shift needs amplitude_mm >= 0, radius_mm > 0.68 x amplitude_mm, a non-zero direction");
  if (!(s.bias_amplitude >= 0 && s.bias_amplitude < 1 && s.noise_fraction >= 0 && s.label_noise_mm >= 0 &&
        s.label_noise_correlation_mm > 0 && s.min_jacobian > 0 && s.min_jacobian < 1))
    fail("bias in [0,1), noise >= 0, correlation > 0 and min_jacobian in (0,1) are required");
}

}  // namespace

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
  if ((sk.enabled || spec.retractor.enabled) && !found)
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
    resection_up_ = sk.enabled ? Eigen::Vector3d(-gravity_) : Eigen::Vector3d(resection_centre_ - centroid_);
    if (resection_up_.norm() < 1e-9) resection_up_ = -gravity_;
    resection_up_.normalize();
    if (rs.collapse_mm >= 0.8 * resection_radius_)
      throw InputError("phantom '" + spec.name + "': collapse_mm must be below 0.8 x the cavity radius (" +
                       std::to_string(resection_radius_) + " mm)");
  }

  const auto& rt = spec.retractor;
  retractor_push_ = rt.push ? rt.push->normalized() : Eigen::Vector3d(-outward);
  // The blade's long axis: any unit vector normal to the push, turned by the angle.
  Eigen::Vector3d any = std::abs(retractor_push_.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d e1 = (any - any.dot(retractor_push_) * retractor_push_).normalized();
  retractor_long_ = Eigen::AngleAxisd(rt.blade_angle_deg * kPi / 180, retractor_push_) * e1;
  retractor_across_ = retractor_push_.cross(retractor_long_);
  place_retractor();

  rigid_.topLeftCorner<3, 3>() = rotation_deg(spec.rigid.rotation_deg);
  rigid_.topRightCorner<3, 1>() = centroid_ + spec.rigid.translation_mm - rigid_.topLeftCorner<3, 3>() * centroid_;
  rigid_inverse_ = rigid_.inverse();
}

void PhantomDeformation::scale_nonrigid(double factor) {
  scale_ *= factor;
  place_retractor();
}

// The blade rests on the cortex where the craniotomy point has moved to.
void PhantomDeformation::place_retractor() {
  Eigen::Vector3d p = craniotomy_ + shift(craniotomy_);
  p += sink(p);
  p += swell(p);
  p += collapse(p);
  retractor_centre_ = p + spec_.retractor.offset_mm;
}

double PhantomDeformation::resection_cut_mm(const Eigen::Vector3d& p) const {
  const double f = spec_.resection.resected_fraction;
  if (!spec_.resection.enabled || f >= 1) return -1e9;
  const double level = resection_radius_ * (1 - 2 * f);  // along up, from the centre
  return level - (p - resection_centre_).dot(resection_up_);
}

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
  const double taper = 1.0 - smoothstep((depth - 0.5 * brain_depth_mm_) / (0.5 * brain_depth_mm_));
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

// The dent: along the push, full under the blade at and above the dented
// surface, Gaussian with depth below it. Its derivative along the push is at
// least -0.86 depth/decay > -0.9 (checked), so the dent is invertible.
Eigen::Vector3d PhantomDeformation::retract(const Eigen::Vector3d& p) const {
  const auto& s = spec_.retractor;
  if (!s.enabled) return Eigen::Vector3d::Zero();
  const Eigen::Vector3d r = p - retractor_centre_;
  const double depth = std::max(0.0, r.dot(retractor_push_)) / s.depth_decay_mm;
  const double beyond_blade = std::max(0.0, std::abs(r.dot(retractor_long_)) - s.half_length_mm) / s.half_width_mm;
  const double across = r.dot(retractor_across_) / s.half_width_mm;
  const double a = scale_ * s.depth_mm * std::exp(-depth * depth - 0.5 * beyond_blade * beyond_blade - 0.5 * across * across);
  return a * retractor_push_;
}

Eigen::Vector3d PhantomDeformation::shift(const Eigen::Vector3d& p) const {
  const auto& s = spec_.midline_shift;
  if (!s.enabled) return Eigen::Vector3d::Zero();
  const double q = (p - centroid_ - s.centre_offset_mm).squaredNorm() / (s.radius_mm * s.radius_mm);
  return scale_ * s.amplitude_mm * std::exp(-0.5 * q) * s.direction.normalized();
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
  Eigen::Vector3d p = preop_mm + shift(preop_mm);
  p += sink(p);
  p += swell(p);
  p += collapse(p);
  p += retract(p);
  return (rigid_ * p.homogeneous()).head<3>();
}

Eigen::Vector3d PhantomDeformation::inverse(const Eigen::Vector3d& intraop_mm) const {
  Eigen::Vector3d y = (rigid_inverse_ * intraop_mm.homogeneous()).head<3>();
  if (spec_.retractor.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return retract(q); });
  if (spec_.resection.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return collapse(q); });
  if (spec_.swelling.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return swell(q); });
  if (spec_.sinking.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return sink(q); });
  if (spec_.midline_shift.enabled) y = invert_component(y, [this](const Eigen::Vector3d& q) { return shift(q); });
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

}  // namespace brainshift
