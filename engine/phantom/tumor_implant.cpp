#include "phantom/tumor_implant.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <random>

#include "core/errors.h"

namespace brainshift {
namespace {

// Relative radius as a function of direction: a few random low-order
// harmonics (first- and second-degree terms in the unit direction), so the
// tumor is lobulated but star-shaped and smooth.
class LobulatedRadius {
 public:
  LobulatedRadius(double lobulation, std::uint64_t seed) : lobulation_(lobulation) {
    std::mt19937_64 rng(seed);
    std::normal_distribution<double> normal(0, 1);
    for (auto& d : axes_) d = Eigen::Vector3d(normal(rng), normal(rng), normal(rng)).normalized();
    for (auto& w : weights_) w = normal(rng);
  }
  double at(const Eigen::Vector3d& unit) const {
    double f = 0;
    for (std::size_t k = 0; k < axes_.size(); ++k) {
      const double c = unit.dot(axes_[k]);
      f += weights_[k] * (k % 2 == 0 ? 0.5 * c : c * c - 1.0 / 3.0);
    }
    return 1.0 + lobulation_ * std::tanh(f);
  }

 private:
  double lobulation_;
  std::array<Eigen::Vector3d, 6> axes_;
  std::array<double, 6> weights_;
};

Eigen::Vector3d brain_centroid(const LabelImage& labels, const std::array<bool, 65536>& brain) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  double n = 0;
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (brain[labels.at(i, j, k)]) sum += Eigen::Vector3d(i, j, k), n += 1;
  if (n == 0) throw InputError("tumor implant: no brain label in the preop labels");
  const Eigen::Vector3d v = sum / n;
  return labels.grid.world_mm(v.x(), v.y(), v.z());
}

bool inside_brain(const LabelImage& labels, const std::array<bool, 65536>& brain, const Eigen::Vector3d& p) {
  const Eigen::Vector3d v = (labels.grid.voxel_from_world() * p.homogeneous()).head<3>();
  const int i = static_cast<int>(std::lround(v.x())), j = static_cast<int>(std::lround(v.y())),
            k = static_cast<int>(std::lround(v.z()));
  return labels.grid.contains(i, j, k) && brain[labels.at(i, j, k)];
}

double median_in(const ImageF& t1, const LabelImage& labels, const std::array<bool, 65536>& set) {
  std::vector<float> values;
  for (std::size_t v = 0; v < t1.voxels.size(); ++v)
    if (set[labels.voxels[v]]) values.push_back(t1.voxels[v]);
  if (values.empty()) return 0;
  std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
  return values[values.size() / 2];
}

}  // namespace

TumorImplantResult implant_tumor(ImageF& t1, LabelImage& labels, const TumorImplantSpec& spec) {
  if (!t1.grid.same_geometry(labels.grid) || t1.voxels.size() != labels.voxels.size())
    throw InputError("tumor implant: the T1 and the labels must share one grid");
  if (!(spec.radius_mm > 0 && spec.depth_mm >= 0 && spec.lobulation >= 0 && spec.lobulation < 0.5 &&
        spec.direction.norm() > 0 && spec.cyst_radius_fraction >= 0 && spec.cyst_radius_fraction < 1))
    throw InputError("tumor implant: radius > 0, depth >= 0, lobulation in [0, 0.5), a direction and a cyst's "
                     "radius fraction in [0, 1) are required");
  std::array<bool, 65536> brain{}, replaceable{};
  for (auto l : spec.brain_labels) brain[l] = true;
  for (auto l : spec.replaceable) replaceable[l] = true;
  TumorImplantResult result;
  if (spec.centre_mm) {
    if (!inside_brain(labels, brain, *spec.centre_mm)) throw InputError("tumor implant: the given centre is not in the brain");
    result.centre_mm = *spec.centre_mm;
  } else {
    const Eigen::Vector3d centroid = brain_centroid(labels, brain);
    const Eigen::Vector3d out = spec.direction.normalized();
    double cortex_t = -1;
    for (double t = 0; t <= 200; t += 0.5)
      if (inside_brain(labels, brain, centroid + t * out)) cortex_t = t;
    if (cortex_t <= spec.depth_mm) throw InputError("tumor implant: the ray from the brain centroid finds no cortex that deep");
    result.centre_mm = centroid + (cortex_t - spec.depth_mm) * out;
  }

  const double brain_median = median_in(t1, labels, brain);
  const float tumor_value = static_cast<float>(spec.intensity_fraction * brain_median);
  std::array<bool, 65536> fluid{};
  for (auto l : spec.fluid_labels) fluid[l] = true;
  const double fluid_median = median_in(t1, labels, fluid);
  const float cyst_value = static_cast<float>(fluid_median > 0 ? fluid_median : 0.3 * brain_median);
  const LobulatedRadius radius(spec.lobulation, spec.seed);
  const double voxel_ml = std::abs(labels.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
  std::size_t taken = 0, cyst_taken = 0;
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        const std::size_t v = labels.grid.index(i, j, k);
        if (!replaceable[labels.voxels[v]]) continue;
        const Eigen::Vector3d r = labels.grid.world_mm(i, j, k) - result.centre_mm;
        const double n = r.norm();
        if (n > 2 * spec.radius_mm) continue;
        const double edge = spec.radius_mm * (n > 0 ? radius.at(r / n) : 1.0);
        // Signed distance to the wall along the ray; a 1 mm partial-volume rim.
        const double s = n - edge;
        if (s > 0.5) continue;
        const double inside = std::clamp(0.5 - s, 0.0, 1.0);
        // The cyst's wall, also with a 1 mm partial-volume rim, inside the tumour's.
        const double in_cyst =
            spec.cyst_radius_fraction > 0 ? std::clamp(0.5 - (n - spec.cyst_radius_fraction * edge), 0.0, 1.0) : 0.0;
        const double solid_value = in_cyst * cyst_value + (1 - in_cyst) * tumor_value;
        t1.voxels[v] = static_cast<float>(inside * solid_value + (1 - inside) * t1.voxels[v]);
        if (s <= 0) {
          labels.voxels[v] = spec.label;
          ++taken;
          if (in_cyst >= 0.5) ++cyst_taken;
        }
      }
  if (taken == 0) throw InputError("tumor implant: the tumor takes no voxel (radius too small or no tissue there)");
  result.volume_ml = taken * voxel_ml;
  result.cyst_ml = cyst_taken * voxel_ml;
  return result;
}

}  // namespace brainshift
