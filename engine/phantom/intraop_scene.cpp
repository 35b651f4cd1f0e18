// The deformed subject as classes and T1 values (intraop_scene.h).
#include "phantom/intraop_scene.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "image/resample.h"
#include "phantom/phantom_support.h"

namespace brainshift {
namespace {

using namespace phantom_detail;

std::vector<float> values_with(const ImageF& t1, const LabelImage& labels, const std::array<bool, 65536>& in) {
  std::vector<float> v;
  for (std::size_t i = 0; i < t1.voxels.size(); ++i)
    if (in[labels.voxels[i]]) v.push_back(t1.voxels[i]);
  return v;
}

// The pull-back x -> phi^-1(x) - x on a lattice of about 2 mm over grid g.
struct LatticeField {
  Grid3 lattice;
  std::vector<float> x, y, z;
};

LatticeField lattice_pullback(const PhantomDeformation& phi, const Grid3& g) {
  LatticeField f;
  const Eigen::Vector3d sp = g.spacing_mm();
  Eigen::Vector3d ratio;
  for (int a = 0; a < 3; ++a) {
    ratio[a] = std::min(1.0, sp[a] / 2.0);
    f.lattice.dims[a] = static_cast<int>(std::ceil((g.dims[a] - 1) * ratio[a])) + 1;
  }
  f.lattice.world_from_voxel = g.world_from_voxel;
  f.lattice.world_from_voxel.topLeftCorner<3, 3>() = g.world_from_voxel.topLeftCorner<3, 3>() * ratio.cwiseInverse().asDiagonal();
  f.x.assign(f.lattice.voxel_count(), 0.f);
  f.y = f.x;
  f.z = f.x;
  parallel_slices(f.lattice.dims[2], [&](int k) {
    for (int j = 0; j < f.lattice.dims[1]; ++j)
      for (int i = 0; i < f.lattice.dims[0]; ++i) {
        const Eigen::Vector3d x = f.lattice.world_mm(i, j, k);
        const Eigen::Vector3d u = phi.inverse(x) - x;
        const std::size_t v = f.lattice.index(i, j, k);
        f.x[v] = static_cast<float>(u.x());
        f.y[v] = static_cast<float>(u.y());
        f.z[v] = static_cast<float>(u.z());
      }
  });
  return f;
}

}  // namespace

IntraopScene make_intraop_scene(const ImageF& preop_t1, const LabelImage& preop_labels, const PhantomSpec& spec,
                                const PhantomDeformation& phi, const IntraopSceneSpec& s) {
  if (!preop_t1.grid.same_geometry(preop_labels.grid) || preop_t1.voxels.size() != preop_labels.voxels.size())
    throw InputError("intraop scene '" + spec.name + "': the preop T1 and labels must share one grid");
  if (!(s.gap_fluid_fraction >= 0 && s.gap_fluid_fraction <= 1 && s.csf_rim_mm >= 0))
    throw InputError("intraop scene '" + spec.name + "': gap_fluid_fraction in [0,1] and csf_rim_mm >= 0 are required");
  IntraopScene scene;
  const auto brain_set = label_set(spec.brain_labels);
  std::array<bool, 65536> vent_set{}, tissue_set{};
  vent_set[spec.ventricle_label] = true;
  for (auto l : spec.brain_labels)
    if (l != spec.ventricle_label && l != spec.resection.tumor_label) tissue_set[l] = true;
  scene.csf_t1 = quantile(values_with(preop_t1, preop_labels, vent_set), 0.5);
  const auto tissue = values_with(preop_t1, preop_labels, tissue_set);
  scene.gm_t1 = quantile(tissue, 0.30);
  scene.wm_t1 = quantile(tissue, 0.85);
  scene.brain_median_t1 = quantile(values_with(preop_t1, preop_labels, brain_set), 0.5);
  if (scene.csf_t1 <= 0) scene.csf_t1 = 0.3 * scene.gm_t1;

  const ImageF sd_brain = signed_distance_mm(mask_of_labels(preop_labels, spec.brain_labels));
  const bool resect = spec.resection.enabled;
  ImageF sd_tumor;
  if (resect && phi.resection_uses_tumor_label()) sd_tumor = signed_distance_mm(mask_of_labels(preop_labels, {spec.resection.tumor_label}));
  const GridSampler sdb(sd_brain.grid), sdt(resect && phi.resection_uses_tumor_label() ? sd_tumor.grid : sd_brain.grid),
      t1s(preop_t1.grid);
  // As make_phantom: the cavity is the resected region cut by the partial
  // resection's plane.
  auto cavity_distance = [&](const Eigen::Vector3d& p) -> double {
    if (!resect) return 1e9;
    const double region = phi.resection_uses_tumor_label() ? sdt.linear(sd_tumor.voxels, p, 1e3f)
                                                           : (p - phi.resection_centre_mm()).norm() - phi.resection_radius_mm();
    return std::max(region, phi.resection_cut_mm(p));
  };
  const Eigen::Vector3d down = phi.gravity();
  const double cavity_radius = phi.resection_radius_mm();
  const double blood_level = cavity_radius * (1 - 2 * spec.resection.blood_fill_fraction);  // along up from the centre
  const double sunk_mm = spec.sinking.enabled ? spec.sinking.cortex_mm * phi.nonrigid_scale() : 0;
  const double fluid_height = -(1 - s.gap_fluid_fraction) * sunk_mm;  // above the craniotomy point, along -gravity

  Grid3 g = preop_t1.grid;
  g.world_from_voxel = phi.intraop_from_preop_rigid() * preop_t1.grid.world_from_voxel;
  const Eigen::Matrix4d preop_from_intraop = phi.intraop_from_preop_rigid().inverse();
  const LatticeField u = lattice_pullback(phi, g);
  const GridSampler lat(u.lattice);
  scene.t1 = ImageF(g, 0.f);
  scene.classes = Image3<std::uint8_t>(g, static_cast<std::uint8_t>(SceneClass::air));
  const float fluid = static_cast<float>(scene.csf_t1);
  const float blood = static_cast<float>(spec.resection.blood_t1_relative * scene.brain_median_t1);
  parallel_slices(g.dims[2], [&](int k) {
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        const Eigen::Vector3d p = x + Eigen::Vector3d(lat.linear(u.x, x, 0.f), lat.linear(u.y, x, 0.f), lat.linear(u.z, x, 0.f));
        const double d_brain = sdb.linear(sd_brain.voxels, p, 1e3f);
        SceneClass c;
        float value;
        if (d_brain < 0 && cavity_distance(p) >= 0) {
          c = SceneClass::tissue;
          value = t1s.linear(preop_t1.voxels, p, 0.f);
        } else if (d_brain < 0) {
          // Blood settles on the dependent side of the cavity.
          const bool in_blood = (p - phi.resection_centre_mm()).dot(-down) < blood_level;
          c = in_blood ? SceneClass::blood : SceneClass::cavity_fluid;
          value = in_blood ? blood : fluid;
        } else {
          const Eigen::Vector3d q = (preop_from_intraop * x.homogeneous()).head<3>();
          const double d_before = sdb.linear(sd_brain.voxels, q, 1e3f);
          if (d_before < 0) {  // where the brain was: the gap
            const bool wet = (q - phi.craniotomy_mm()).dot(-down) < fluid_height || !spec.sinking.enabled;
            c = wet ? SceneClass::gap_fluid : SceneClass::air;
            value = wet ? fluid : 0.f;
          } else {
            value = t1s.linear(preop_t1.voxels, q, 0.f);
            const bool csf = d_before < s.csf_rim_mm && value < 0.5 * (scene.csf_t1 + scene.gm_t1);
            c = csf ? SceneClass::extracerebral_csf : value > 0 ? SceneClass::head : SceneClass::air;
          }
        }
        scene.classes.voxels[v] = static_cast<std::uint8_t>(c);
        scene.t1.voxels[v] = value;
      }
  });
  return scene;
}

}  // namespace brainshift
