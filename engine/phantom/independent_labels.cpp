#include "phantom/independent_labels.h"

#include <algorithm>
#include <cmath>
#include <deque>
#include <limits>

#include "atlas/default_atlas.h"
#include "core/errors.h"
#include "core/label_colour.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "image/nifti_io.h"
#include "image/resample.h"

namespace brainshift {
namespace {

Mask unsmoothed_brain(const ImageF& bet_on_t1) {
  const Mask m = threshold(bet_on_t1, 1e-3f, std::numeric_limits<float>::max());
  return fill_holes(largest_component(m, 26));
}

// 26-connected growth inside `allowed` from the seed voxels.
Mask grow(const Mask& allowed, const Mask& seeds) {
  const Grid3& g = allowed.grid;
  Mask out(g, 0);
  std::deque<std::array<int, 3>> queue;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        if (seeds.at(i, j, k) && allowed.at(i, j, k)) {
          out.at(i, j, k) = 1;
          queue.push_back({i, j, k});
        }
  while (!queue.empty()) {
    const auto [i, j, k] = queue.front();
    queue.pop_front();
    for (int dk = -1; dk <= 1; ++dk)
      for (int dj = -1; dj <= 1; ++dj)
        for (int di = -1; di <= 1; ++di) {
          const int a = i + di, b = j + dj, c = k + dk;
          if (!g.contains(a, b, c) || out.at(a, b, c) || !allowed.at(a, b, c)) continue;
          out.at(a, b, c) = 1;
          queue.push_back({a, b, c});
        }
  }
  return out;
}

}  // namespace

IndependentLabels build_independent_labels(const ImageF& t1, const std::filesystem::path& dir,
                                           const IndependentLabelParameters& p) {
  const Grid3& g = t1.grid;
  const ImageF bet_src = read_scalar_image(dir / "ch2bet.nii.gz");
  const Mask brain = unsmoothed_brain(bet_src.grid.same_geometry(g) ? bet_src : resample_linear(bet_src, g));
  const Mask deep = erode(brain, p.erosion_mm);
  Mask candidates(g, 0), seeds(g, 0);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        if (!deep.voxels[v] || !(t1.voxels[v] < p.csf_max) || x.z() < p.z_floor_mm) continue;
        // The third ventricle and the cisterns below the bodies, on the midline.
        if (std::abs(x.x()) < p.midline_half_width_mm && x.z() < p.midline_top_mm) continue;
        candidates.voxels[v] = 1;
        // The bodies of the lateral ventricles, beside the midline above the thalamus.
        seeds.voxels[v] = std::abs(x.x()) > 2 && std::abs(x.x()) < p.seed_box_half_width_mm && x.y() > -30 &&
                          x.y() < 20 && x.z() > 10 && x.z() < 30;
      }
  const Mask ventricles = grow(candidates, seeds);
  IndependentLabels out;
  out.ventricles_ml = volume_ml(ventricles);
  if (out.ventricles_ml < p.min_ml)
    throw InputError("independent labels: ventricle growth reached only " + std::to_string(out.ventricles_ml) +
                     " ml (is " + (dir / "ch2.nii.gz").string() + " the Colin27 T1?)");
  connected_components(ventricles, 6, &out.ventricle_components);

  out.labels = compose_atlas_labels(brain, ventricles, jhu_corticospinal_tract(dir, g));
  out.brain_ml = volume_ml(brain);
  out.cst_ml = volume_ml(mask_of_labels(out.labels, {atlas_labels::corticospinal_tract}));
  return out;
}

}  // namespace brainshift
