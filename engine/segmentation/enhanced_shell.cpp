#include "segmentation/enhanced_shell.h"

#include <algorithm>
#include <vector>

#include "image/distance_map.h"
#include "image/image_stats.h"

namespace brainshift::segmentation {

EnhancedShell enhanced_shell(const ImageF& image, const ImageF& bias, const Mask& brain,
                             const std::vector<GaussianClass>& classes, const EnhancedShellParameters& params) {
  EnhancedShell out;
  const auto untested = [&](const char* why) {
    out.why_not_tested = why;
    out.metrics = {{"tested", false}, {"why", why}};
    return out;
  };
  if (!image.grid.same_geometry(brain.grid) || !bias.grid.same_geometry(brain.grid))
    return untested("the image, its bias and the segmentation are on different grids");
  if (fluid_is_bright(classes)) return untested("a bright-fluid image: its CSF rim is bright by nature");
  std::vector<float> inside;
  for (std::size_t v = 0; v < brain.voxels.size(); ++v)
    if (brain.voxels[v]) inside.push_back(image.voxels[v] / bias.voxels[v]);
  if (inside.empty()) return untested("no brain");
  std::nth_element(inside.begin(), inside.begin() + inside.size() / 2, inside.end());
  const double bright = params.bright_fraction_of_brain_median * inside[inside.size() / 2];
  // Both distance maps on the brain's box grown beyond the deepest distance
  // either needs: every voxel within that reach of the brain lies in it, so
  // the figures are those of the whole grid, at the neighbourhood's cost.
  const double voxel_mm = brain.grid.spacing_mm().maxCoeff();
  const double layer_mm = std::max(params.inner_mm, voxel_mm);
  const VoxelBox box = grow_box(bounding_box_voxels(brain), brain.grid,
                                std::max(params.outer_mm, 2 * layer_mm) + 2 * voxel_mm);
  const Mask brain_box = crop_to_box(brain, box);
  const Grid3& g = brain_box.grid;
  const auto full_index = [&](std::size_t b) {
    const int i = static_cast<int>(b % g.dims[0]), j = static_cast<int>((b / g.dims[0]) % g.dims[1]),
              k = static_cast<int>(b / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    return brain.grid.index(i + box.lo[0], j + box.lo[1], k + box.lo[2]);
  };
  const ImageF outside_mm = distance_to_mask_mm(brain_box, params.outer_mm + voxel_mm);
  std::size_t shell = 0, lit = 0;
  for (std::size_t b = 0; b < brain_box.voxels.size(); ++b) {
    const float d = outside_mm.voxels[b];
    if (!(d > params.inner_mm && d <= params.outer_mm)) continue;
    ++shell;
    const std::size_t v = full_index(b);
    lit += image.voxels[v] / bias.voxels[v] >= bright;
  }
  // A shell of a few hundred voxels (a field of view that holds little
  // of the brain's surround) says nothing.
  if (shell < 1000) return untested("too little of the brain's surround is in the image");
  // Where the segmentation took the shell in, it lies on the outline: the
  // outline's outer layer is then as bright as the layer beneath it, where
  // an unenhanced brain's is darker (the cortex's partial volume with the
  // CSF). Layers of at least a voxel.
  Mask outside(g, 0);
  for (std::size_t b = 0; b < brain_box.voxels.size(); ++b) outside.voxels[b] = !brain_box.voxels[b];
  const ImageF depth_mm = distance_to_mask_mm(outside, 2 * layer_mm + voxel_mm);
  double outer_sum = 0, beneath_sum = 0;
  std::size_t outer_n = 0, beneath_n = 0;
  for (std::size_t b = 0; b < brain_box.voxels.size(); ++b) {
    const float d = depth_mm.voxels[b];
    if (!brain_box.voxels[b] || !(d > 0)) continue;
    const std::size_t v = full_index(b);
    const double value = image.voxels[v] / bias.voxels[v];
    if (d <= layer_mm) {
      outer_sum += value;
      ++outer_n;
    } else if (d <= 2 * layer_mm) {
      beneath_sum += value;
      ++beneath_n;
    }
  }
  out.tested = true;
  out.bright_fraction = static_cast<double>(lit) / static_cast<double>(shell);
  out.surface_ratio = outer_n && beneath_n ? (outer_sum / outer_n) / (beneath_sum / beneath_n) : 0.0;
  out.enhanced = out.bright_fraction > params.max_bright_fraction ||
                 (out.bright_fraction > params.outline_bright_fraction &&
                  out.surface_ratio > params.outline_surface_ratio);
  out.metrics = {{"tested", true},
                 {"bright_fraction", out.bright_fraction},
                 {"limit", params.max_bright_fraction},
                 {"shell_mm", {params.inner_mm, params.outer_mm}},
                 {"surface_ratio", out.surface_ratio},
                 {"with_outline", {{"bright_fraction", params.outline_bright_fraction},
                                   {"surface_ratio", params.outline_surface_ratio}}},
                 {"layer_mm", layer_mm},
                 {"enhanced", out.enhanced}};
  return out;
}

}  // namespace brainshift::segmentation
