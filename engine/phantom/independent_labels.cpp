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

// The median T1 of a mask's voxels (0 when empty).
double median_t1(const ImageF& t1, const Mask& m) {
  std::vector<float> x;
  for (std::size_t v = 0; v < m.voxels.size(); ++v)
    if (m.voxels[v]) x.push_back(t1.voxels[v]);
  if (x.empty()) return 0;
  std::nth_element(x.begin(), x.begin() + static_cast<std::ptrdiff_t>(x.size() / 2), x.end());
  return x[x.size() / 2];
}

// Dark voxels of the deep brain (T1 below `below`) outside the excluded
// regions, and among them the seeds in the ventricle bodies.
std::pair<Mask, Mask> candidates_and_seeds(const ImageF& t1, const Mask& deep, double below,
                                           const IndependentLabelParameters& p) {
  const Grid3& g = t1.grid;
  Mask candidates(g, 0), seeds(g, 0);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        if (!deep.voxels[v] || !(t1.voxels[v] < below) || x.z() < p.z_floor_mm) continue;
        // The third ventricle and the cisterns below the bodies, on the midline.
        if (std::abs(x.x()) < p.midline_half_width_mm && x.z() < p.midline_top_mm) continue;
        candidates.voxels[v] = 1;
        // The bodies of the lateral ventricles, beside the midline above the thalamus.
        seeds.voxels[v] = std::abs(x.x()) > 2 && std::abs(x.x()) < p.seed_box_half_width_mm && x.y() > -30 &&
                          x.y() < 20 && x.z() > 10 && x.z() < 30;
      }
  return {candidates, seeds};
}

}  // namespace

IndependentLabels build_independent_labels(const ImageF& t1, const std::filesystem::path& dir,
                                           const IndependentLabelParameters& p) {
  const Grid3& g = t1.grid;
  const ImageF bet_src = read_scalar_image(dir / "ch2bet.nii.gz");
  const Mask brain = unsmoothed_brain(bet_src.grid.same_geometry(g) ? bet_src : resample_linear(bet_src, g));
  const Mask deep = erode(brain, p.erosion_mm);
  // First the surely-fluid core, then its wall out to where a voxel is half
  // fluid: T1 midway between the core's and the tissue's a few mm around it.
  // The wall only: growing again at that level would run along the partial
  // volume of every sulcus and deep-grey boundary the core comes near.
  const auto [sure, sure_seeds] = candidates_and_seeds(t1, deep, p.csf_max, p);
  Mask ventricles = grow(sure, sure_seeds);
  IndependentLabels out;
  out.wall_t1 = p.csf_max;
  if (p.wall_at_half_fluid && count_nonzero(ventricles) > 0) {
    const Mask near = dilate(ventricles, p.wall_shell_mm[0]), far = dilate(ventricles, p.wall_shell_mm[1]);
    Mask shell(g, 0);
    for (std::size_t v = 0; v < shell.voxels.size(); ++v)
      shell.voxels[v] = far.voxels[v] && !near.voxels[v] && brain.voxels[v];
    out.fluid_t1 = median_t1(t1, ventricles);
    out.tissue_t1 = median_t1(t1, shell);
    out.wall_t1 = 0.5 * (out.fluid_t1 + out.tissue_t1);
    const Mask half = candidates_and_seeds(t1, deep, out.wall_t1, p).first;
    for (std::size_t v = 0; v < ventricles.voxels.size(); ++v)
      ventricles.voxels[v] = ventricles.voxels[v] || (near.voxels[v] && half.voxels[v]);
  }
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
