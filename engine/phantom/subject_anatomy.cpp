// Other heads from the atlas (subject_anatomy.h): the warp's steps, its
// inverse, and the subject's images.
#include "phantom/subject_anatomy.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>
#include <random>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "image/resample.h"
#include "phantom/phantom_artefacts.h"
#include "phantom/phantom_support.h"

namespace brainshift {
namespace {

using namespace phantom_detail;

// Each step's displacement has a Lipschitz constant below this: the fixed
// point of its inverse then gains a factor 2 per iteration.
constexpr double kStepLipschitz = 0.5;

void check(const SubjectSpec& s) {
  auto fail = [&](const std::string& what) { throw InputError("subject '" + s.name + "': " + what); };
  if (!(s.axis_scale.minCoeff() >= 0.8 && s.axis_scale.maxCoeff() <= 1.25)) fail("axis_scale must be in [0.8, 1.25]");
  if (!(s.reshape_bumps >= 0 && s.reshape_bumps <= 50 && s.reshape_amplitude_mm >= 0 && s.reshape_width_mm > 0 &&
        0.61 * s.reshape_amplitude_mm < kStepLipschitz * s.reshape_width_mm))
    fail("reshaping needs 0-50 bumps and amplitude_mm < 0.82 x width_mm (each bump invertible)");
  if (!(s.ventricle_volume_factor >= 0.5 && s.ventricle_volume_factor <= 4 && s.ventricle_decay_mm > 0))
    fail("ventricle_volume_factor must be in [0.5, 4] and ventricle_decay_mm > 0");
  if (s.mass_effect && s.tumor) fail("a mass effect brings its own tumour: give one or the other");
  if (s.mass_effect && !(s.mass_effect->radius_mm > 0 && s.mass_effect->push_mm >= 0 && s.mass_effect->gap_mm >= 0 &&
                         s.mass_effect->side.norm() > 0))
    fail("mass effect needs radius_mm > 0, push_mm >= 0, gap_mm >= 0 and a side");
}

// A vector field on a grid, sampled trilinearly (zero outside).
struct SampledField {
  Grid3 grid;
  std::vector<float> x, y, z;
  std::unique_ptr<GridSampler> sampler;
  Eigen::Vector3d at(const Eigen::Vector3d& p) const {
    return {sampler->linear(x, p, 0.f), sampler->linear(y, p, 0.f), sampler->linear(z, p, 0.f)};
  }
};

// Largest Frobenius norm of the field's gradient over its grid (central
// differences in world mm): a bound on its Lipschitz constant there.
double max_gradient(const SampledField& f) {
  const Grid3& g = f.grid;
  const Eigen::Matrix3d voxel_from_world = g.world_from_voxel.topLeftCorner<3, 3>().inverse();
  double worst = 0;
  for (int k = 1; k + 1 < g.dims[2]; ++k)
    for (int j = 1; j + 1 < g.dims[1]; ++j)
      for (int i = 1; i + 1 < g.dims[0]; ++i) {
        Eigen::Matrix3d d_dvoxel;
        const std::size_t c[3][2] = {{g.index(i - 1, j, k), g.index(i + 1, j, k)},
                                     {g.index(i, j - 1, k), g.index(i, j + 1, k)},
                                     {g.index(i, j, k - 1), g.index(i, j, k + 1)}};
        for (int a = 0; a < 3; ++a)
          d_dvoxel.col(a) = 0.5 * Eigen::Vector3d(f.x[c[a][1]] - f.x[c[a][0]], f.y[c[a][1]] - f.y[c[a][0]],
                                                  f.z[c[a][1]] - f.z[c[a][0]]);
        worst = std::max(worst, (d_dvoxel * voxel_from_world).norm());
      }
  return worst;
}

std::size_t count_label(const LabelImage& labels, std::uint16_t l) {
  return static_cast<std::size_t>(std::count(labels.voxels.begin(), labels.voxels.end(), l));
}

double voxel_ml(const Grid3& g) { return std::abs(g.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0; }

}  // namespace

SubjectWarp::SubjectWarp(const LabelImage& labels, const SubjectSpec& spec) : spec_(spec) {
  check(spec);
  if (labels.grid.voxel_count() == 0 || labels.voxels.size() != labels.grid.voxel_count())
    throw InputError("subject '" + spec.name + "': the atlas label image is empty");
  const Mask brain = mask_of_labels(labels, spec.brain_labels);
  if (count_nonzero(brain) == 0) throw InputError("subject '" + spec.name + "': no brain label in the atlas labels");
  centroid_ = centroid_mm(brain);
  if (spec.ventricle_volume_factor != 1) add_ventricle_enlargement(labels);
  if (spec.mass_effect) add_mass_effect(labels);
  if (spec.reshape_bumps > 0) add_reshaping(labels);
  description_["steps"] = steps_.size();
  description_["axis_scale"] = {spec.axis_scale.x(), spec.axis_scale.y(), spec.axis_scale.z()};
}

void SubjectWarp::add_ventricle_enlargement(const LabelImage& labels) {
  const Mask vent = mask_of_labels(labels, {spec_.ventricle_label});
  if (count_nonzero(vent) == 0) throw InputError("subject '" + spec_.name + "': no ventricle label to enlarge");
  const double decay = spec_.ventricle_decay_mm;
  const Mask crop = crop_to_box(vent, grow_box(bounding_box_voxels(vent), vent.grid, 3 * decay + 10));
  // The outward normal: gradient of the smoothed signed distance (smooth
  // across the medial axis, where it vanishes by symmetry).
  ImageF sd = signed_distance_mm(crop);
  const Eigen::Vector3d sp = crop.grid.spacing_mm();
  gaussian_smooth_voxels(sd, Eigen::Vector3d(1.5 / sp.x(), 1.5 / sp.y(), 1.5 / sp.z()));
  auto field = std::make_shared<SampledField>();
  field->grid = crop.grid;
  const Grid3& g = crop.grid;
  field->x.assign(g.voxel_count(), 0.f);
  field->y = field->x;
  field->z = field->x;
  const Eigen::Matrix3d world_from_voxel_t_inv = g.world_from_voxel.topLeftCorner<3, 3>().inverse().transpose();
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        auto at = [&](int a, int b, int c) {
          return sd.at(std::clamp(a, 0, g.dims[0] - 1), std::clamp(b, 0, g.dims[1] - 1), std::clamp(c, 0, g.dims[2] - 1));
        };
        const Eigen::Vector3d d_voxel(0.5 * (at(i + 1, j, k) - at(i - 1, j, k)), 0.5 * (at(i, j + 1, k) - at(i, j - 1, k)),
                                      0.5 * (at(i, j, k + 1) - at(i, j, k - 1)));
        const double s = sd.at(i, j, k);
        const double w = s <= 0 ? 1.0 : std::exp(-(s / decay) * (s / decay));
        const Eigen::Vector3d v = w * (world_from_voxel_t_inv * d_voxel);
        const std::size_t idx = g.index(i, j, k);
        field->x[idx] = static_cast<float>(v.x());
        field->y[idx] = static_cast<float>(v.y());
        field->z[idx] = static_cast<float>(v.z());
      }
  field->sampler = std::make_unique<GridSampler>(g);
  const double lipschitz = std::max(1e-6, max_gradient(*field));

  // Amplitude by bisection on the forward volume: sum over ventricle voxels
  // of det(d psi/d p) (one-sided differences of 0.25 mm).
  std::vector<Eigen::Vector3d> vent_points;
  for (int k = 0; k < vent.grid.dims[2]; ++k)
    for (int j = 0; j < vent.grid.dims[1]; ++j)
      for (int i = 0; i < vent.grid.dims[0]; ++i)
        if (vent.at(i, j, k)) vent_points.push_back(vent.grid.world_mm(i, j, k));
  auto steps_for = [&](double amplitude) { return std::max(1, static_cast<int>(std::ceil(amplitude * lipschitz / kStepLipschitz))); };
  auto flow = [&](Eigen::Vector3d p, double amplitude) {
    const int n = steps_for(amplitude);
    for (int s = 0; s < n; ++s) p += (amplitude / n) * field->at(p);
    return p;
  };
  auto volume_factor = [&](double amplitude) {
    std::vector<double> per_slice(2, 0.0);
    parallel_slices(2, [&](int t) {
      for (std::size_t q = static_cast<std::size_t>(t); q < vent_points.size(); q += 2) {
        const Eigen::Vector3d& p = vent_points[q];
        const double h = 0.25;
        const Eigen::Vector3d y0 = flow(p, amplitude);
        Eigen::Matrix3d jac;
        for (int a = 0; a < 3; ++a) jac.col(a) = (flow(p + h * Eigen::Vector3d::Unit(a), amplitude) - y0) / h;
        per_slice[t] += jac.determinant();
      }
    });
    return (per_slice[0] + per_slice[1]) / static_cast<double>(vent_points.size());
  };
  const double target = spec_.ventricle_volume_factor;
  double lo = target > 1 ? 0.0 : -10.0, hi = target > 1 ? 15.0 : 0.0;
  for (int it = 0; it < 16; ++it) {
    const double mid = 0.5 * (lo + hi);
    (volume_factor(mid) < target ? lo : hi) = mid;
  }
  const double amplitude = 0.5 * (lo + hi);
  const int n = steps_for(std::abs(amplitude));
  for (int s = 0; s < n; ++s)
    steps_.push_back([field, a = amplitude / n](const Eigen::Vector3d& p) -> Eigen::Vector3d { return a * field->at(p); });
  description_["ventricle_enlargement"] = {{"wall_amplitude_mm", amplitude},
                                           {"euler_steps", n},
                                           {"field_lipschitz_per_mm", lipschitz},
                                           {"forward_volume_factor", volume_factor(amplitude)}};
}

void SubjectWarp::add_mass_effect(const LabelImage& labels) {
  const MassEffectSpec& m = *spec_.mass_effect;
  const Mask vent = mask_of_labels(labels, {spec_.ventricle_label});
  if (count_nonzero(vent) == 0) throw InputError("subject '" + spec_.name + "': a mass effect needs a ventricle to press on");
  // Beside the ventricle's outermost point on that side.
  const Eigen::Vector3d side = m.side.normalized();
  Eigen::Vector3d wall = Eigen::Vector3d::Zero();
  double best = -std::numeric_limits<double>::infinity();
  for (int k = 0; k < vent.grid.dims[2]; ++k)
    for (int j = 0; j < vent.grid.dims[1]; ++j)
      for (int i = 0; i < vent.grid.dims[0]; ++i)
        if (vent.at(i, j, k)) {
          const Eigen::Vector3d p = vent.grid.world_mm(i, j, k);
          if (p.dot(side) > best) best = p.dot(side), wall = p;
        }
  const Eigen::Vector3d centre = wall + m.gap_mm * side;
  // Radial push m(r) = push/R exp(1/2 - r^2/2R^2) r: peak push at R, its
  // gradient at most 1.65 push/R (at the centre).
  const int n = std::max(1, static_cast<int>(std::ceil(1.65 * m.push_mm / m.radius_mm / kStepLipschitz)));
  const double a = m.push_mm / m.radius_mm / n, r2 = m.radius_mm * m.radius_mm;
  for (int s = 0; s < n; ++s)
    steps_.push_back([centre, a, r2](const Eigen::Vector3d& p) -> Eigen::Vector3d {
      const Eigen::Vector3d r = p - centre;
      return a * std::exp(0.5 - 0.5 * r.squaredNorm() / r2) * r;
    });
  mass_centre_ = centre;
  push_end_ = steps_.size();
  description_["mass_effect"] = {{"centre_atlas_mm", {centre.x(), centre.y(), centre.z()}},
                                 {"euler_steps", n}, {"push_mm", m.push_mm}, {"radius_mm", m.radius_mm}};
}

void SubjectWarp::add_reshaping(const LabelImage& labels) {
  std::mt19937_64 rng(spec_.seed * 1000003 + 7);
  std::normal_distribution<double> normal(0, 1);
  std::uniform_real_distribution<double> unit(0.5, 1.0);
  std::uniform_int_distribution<std::size_t> any(0, labels.voxels.size() - 1);
  const auto brain = label_set(spec_.brain_labels);
  const Grid3& g = labels.grid;
  nlohmann::json bumps = nlohmann::json::array();
  for (int b = 0; b < spec_.reshape_bumps; ++b) {
    std::size_t v = any(rng);
    for (int tries = 0; tries < 100000 && !brain[labels.voxels[v]]; ++tries) v = any(rng);
    const int i = static_cast<int>(v % g.dims[0]), j = static_cast<int>((v / g.dims[0]) % g.dims[1]),
              k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    const Eigen::Vector3d centre = g.world_mm(i, j, k);
    const Eigen::Vector3d d = Eigen::Vector3d(normal(rng), normal(rng), normal(rng)).normalized() *
                              (unit(rng) * spec_.reshape_amplitude_mm);
    const double s2 = spec_.reshape_width_mm * spec_.reshape_width_mm;
    steps_.push_back([centre, d, s2](const Eigen::Vector3d& p) -> Eigen::Vector3d {
      return std::exp(-0.5 * (p - centre).squaredNorm() / s2) * d;
    });
    bumps.push_back({{"centre_atlas_mm", {centre.x(), centre.y(), centre.z()}}, {"displacement_mm", {d.x(), d.y(), d.z()}}});
  }
  description_["reshaping"] = {{"width_mm", spec_.reshape_width_mm}, {"bumps", bumps}};
}

Eigen::Vector3d SubjectWarp::invert_step(const Step& f, const Eigen::Vector3d& y) {
  // p + f(p) = y; f is a contraction of ratio < 1/2: 40 iterations reach 1e-12 of the start.
  Eigen::Vector3d p = y - f(y);
  for (int it = 0; it < 60; ++it) {
    const Eigen::Vector3d next = y - f(p);
    const double change = (next - p).squaredNorm();
    p = next;
    if (change < 1e-14) break;
  }
  return p;
}

Eigen::Vector3d SubjectWarp::forward(const Eigen::Vector3d& atlas_mm) const {
  Eigen::Vector3d p = atlas_mm;
  for (const auto& f : steps_) p += f(p);
  return centroid_ + spec_.axis_scale.cwiseProduct(p - centroid_);
}

Eigen::Vector3d SubjectWarp::inverse(const Eigen::Vector3d& subject_mm) const {
  Eigen::Vector3d p = centroid_ + (subject_mm - centroid_).cwiseQuotient(spec_.axis_scale);
  for (auto it = steps_.rbegin(); it != steps_.rend(); ++it) p = invert_step(*it, p);
  return p;
}

Eigen::Vector3d SubjectWarp::tumor_centre_mm() const {
  if (!mass_centre_.allFinite()) return mass_centre_;
  // The push leaves its centre in place; the later steps and the scale move it.
  Eigen::Vector3d p = mass_centre_;
  for (std::size_t s = push_end_; s < steps_.size(); ++s) p += steps_[s](p);
  return centroid_ + spec_.axis_scale.cwiseProduct(p - centroid_);
}

Subject make_subject(const ImageF& atlas_t1, const LabelImage& atlas_labels, const SubjectSpec& spec) {
  const auto t0 = std::chrono::steady_clock::now();
  if (!atlas_t1.grid.same_geometry(atlas_labels.grid) || atlas_t1.voxels.size() != atlas_labels.voxels.size() ||
      atlas_t1.voxels.empty())
    throw InputError("subject '" + spec.name + "': the atlas T1 and labels must share one non-empty grid");
  const SubjectWarp warp(atlas_labels, spec);
  const Grid3& g = atlas_t1.grid;
  // psi^-1 on a lattice of about 2 mm, interpolated to the voxels.
  const Eigen::Vector3d sp = g.spacing_mm();
  Eigen::Vector3d ratio;  // lattice cells per voxel
  Grid3 lattice;
  for (int a = 0; a < 3; ++a) {
    ratio[a] = std::min(1.0, sp[a] / 2.0);
    lattice.dims[a] = static_cast<int>(std::ceil((g.dims[a] - 1) * ratio[a])) + 1;
  }
  lattice.world_from_voxel = g.world_from_voxel;
  lattice.world_from_voxel.topLeftCorner<3, 3>() = g.world_from_voxel.topLeftCorner<3, 3>() * ratio.cwiseInverse().asDiagonal();
  std::vector<float> ux(lattice.voxel_count()), uy(ux.size()), uz(ux.size());
  parallel_slices(lattice.dims[2], [&](int k) {
    for (int j = 0; j < lattice.dims[1]; ++j)
      for (int i = 0; i < lattice.dims[0]; ++i) {
        const Eigen::Vector3d y = lattice.world_mm(i, j, k);
        const Eigen::Vector3d u = warp.inverse(y) - y;
        const std::size_t v = lattice.index(i, j, k);
        ux[v] = static_cast<float>(u.x());
        uy[v] = static_cast<float>(u.y());
        uz[v] = static_cast<float>(u.z());
      }
  });
  Subject out;
  out.name = spec.name;
  out.t1 = ImageF(g, 0.f);
  out.labels = LabelImage(g, 0);
  const GridSampler lat(lattice), src(g);
  parallel_slices(g.dims[2], [&](int k) {
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d y = g.world_mm(i, j, k);
        const Eigen::Vector3d q = y + Eigen::Vector3d(lat.linear(ux, y, 0.f), lat.linear(uy, y, 0.f), lat.linear(uz, y, 0.f));
        const std::size_t v = g.index(i, j, k);
        out.t1.voxels[v] = src.linear(atlas_t1.voxels, q, 0.f);
        out.labels.voxels[v] = src.nearest(atlas_labels.voxels, q, 0);
      }
  });
  nlohmann::json d = warp.description();
  d["name"] = spec.name;
  d["seed"] = spec.seed;
  const double ml = voxel_ml(g);
  d["ventricles_ml"] = {{"atlas", count_label(atlas_labels, spec.ventricle_label) * ml},
                        {"subject", count_label(out.labels, spec.ventricle_label) * ml}};
  d["brain_ml"] = {{"atlas", count_nonzero(mask_of_labels(atlas_labels, spec.brain_labels)) * ml},
                   {"subject", count_nonzero(mask_of_labels(out.labels, spec.brain_labels)) * ml}};
  std::optional<TumorImplantSpec> tumor = spec.tumor;
  if (spec.mass_effect) {
    TumorImplantSpec t;
    t.centre_mm = warp.tumor_centre_mm();
    t.radius_mm = spec.mass_effect->radius_mm;
    t.lobulation = spec.mass_effect->lobulation;
    t.intensity_fraction = spec.mass_effect->intensity_fraction;
    t.cyst_radius_fraction = spec.mass_effect->cyst_radius_fraction;
    t.seed = spec.seed;
    t.label = spec.tumor_label;
    t.brain_labels = spec.brain_labels;
    tumor = t;
  }
  if (tumor) {
    tumor->fluid_labels = {spec.ventricle_label};
    const TumorImplantResult r = implant_tumor(out.t1, out.labels, *tumor);
    d["tumor"] = {{"centre_mm", {r.centre_mm.x(), r.centre_mm.y(), r.centre_mm.z()}}, {"volume_ml", r.volume_ml},
                  {"radius_mm", tumor->radius_mm}, {"cyst_ml", r.cyst_ml}};
  }
  d["seconds"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  out.description = std::move(d);
  return out;
}

}  // namespace brainshift
