#include "segmentation/fluid_rim.h"

#include <cmath>
#include <cstdint>
#include <vector>

#include "image/distance_map.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "segmentation/fluid_caps.h"

namespace brainshift::segmentation {

namespace {

Mask complement(const Mask& m) {
  Mask out = m;
  for (auto& v : out.voxels) v = !v;
  return out;
}

// The face-connected pieces of `candidate` holding at least a cube of the
// rim's thickness: a body of fluid, not a voxel of noise (2-3 sd bright in
// grey matter at SNR 8-12).
Mask fluid_bodies(const Mask& candidate, double max_depth_mm) {
  const Grid3& g = candidate.grid;
  int count = 0;
  const auto pieces = connected_components(candidate, 6, &count);
  std::vector<std::size_t> piece_voxels(static_cast<std::size_t>(count) + 1, 0);
  for (std::size_t v = 0; v < candidate.voxels.size(); ++v) ++piece_voxels[pieces.voxels[v]];
  const double voxel_mm3 = g.spacing_mm().prod();
  Mask body(g, 0);
  for (std::size_t v = 0; v < candidate.voxels.size(); ++v)
    body.voxels[v] = candidate.voxels[v] &&
                     static_cast<double>(piece_voxels[pieces.voxels[v]]) * voxel_mm3 >= std::pow(max_depth_mm, 3);
  return body;
}

}  // namespace

// Why: in a T2-like image the CSF between the cortex and the skull (1-3 mm
// over the convexity) is the brightest tissue there, and the brain holds
// bright tissue of its own (sulcal fluid, oedema), so a parenchyma class
// spans the fluid's partial volume; where the carried outline lies on the
// rim (a first round, or a placement, a voxel or two out) the prior keeps
// the rim in the brain, and the round after inherits it. In a T1 the rim is
// dark, as dark as bone, and falls outside by its intensity alone. A voxel
// at least half fluid is not brain (the partial-volume rule: at the midpoint
// of the two tissues' intensities half of each), and fluid reached from the
// outside within the rim's thickness is the rim. Deeper fluid open to the
// outside is the open-fluid rule's (a gap, a cavity: item 7), and sulci
// deeper than the bound keep their fluid, as every outline counts them.
Mask fluid_rim(const Mask& brain, const Mask& ventricle, const ImageF& image, const std::vector<float>& bias,
               const std::vector<GaussianClass>& classes, const FluidRimBounds& bounds, const Mask& resectable,
               const Eigen::Vector3d& centre_voxel) {
  const Grid3& g = brain.grid;
  const double max_depth_mm = bounds.max_depth_mm;
  Mask rim(g, 0);
  const GaussianClass* fluid = heaviest_class(classes, Tissue::ventricle);
  const GaussianClass* bulk = heaviest_class(classes, Tissue::parenchyma);
  if (max_depth_mm <= 0 || !fluid_is_bright(classes)) return rim;
  // The tissue the rim borders is the cortex: of the major parenchyma
  // classes (kMajorClassWeight), the one nearest the fluid. Against white
  // matter's mean the midpoint fell inside the grey matter of a 1 mm T2
  // and peeled 167 ml of cortex (docs/PERFORMANCE.md 12.18).
  const GaussianClass* cortex = bulk;
  for (const auto& c : classes)
    if (c.tissue == Tissue::parenchyma && c.weight >= kMajorClassWeight && c.mean < fluid->mean && c.mean > cortex->mean)
      cortex = &c;
  const double half_fluid = 0.5 * (fluid->mean + cortex->mean);
  const auto half_fluid_or_more = [&](std::size_t v) {
    return brain.voxels[v] && !ventricle.voxels[v] && image.voxels[v] / bias[v] >= half_fluid;
  };

  // Beyond the fluid, between it and the outside, lies its partial volume
  // with the dura and the inner table: darker than half fluid, so a
  // parenchyma class takes it, and it hides the fluid beneath it from the
  // outside. The brain is never beyond its fluid: such a cap is not brain
  // (caps_beyond_fluid), and the fluid under it is reached from the outside
  // through it. Measured on the hospital suite's T2-like resection: a 1-3 mm
  // shell of intensity ~61 (brain 45, fluid 104) outside the truth
  // (docs/PERFORMANCE.md 12.24); over the vertex 4-5 mm of 30-40 (12.38):
  // thicker caps there, with the fluid looked for as deep as rim and cap,
  // but not beside a cavity, whose walls lie beyond its fluid.
  const double pooled_sd = std::sqrt(0.5 * (fluid->sd * fluid->sd + cortex->sd * cortex->sd));
  const bool thick = bounds.max_cap_mm > max_depth_mm &&
                     fluid->mean - cortex->mean >= bounds.min_separation_sd * pooled_sd;
  const double cap_mm = thick ? bounds.max_cap_mm : max_depth_mm;
  const bool any_resectable = thick && resectable.grid.same_geometry(g) && count_nonzero(resectable) > 0;
  const Mask near_cavity = any_resectable ? dilate(resectable, bounds.cavity_margin_mm) : Mask(g, 0);
  const Mask filled = fill_holes(brain);
  const ImageF depth_mm = distance_to_mask_mm(complement(filled), thick ? max_depth_mm + cap_mm : max_depth_mm);
  Mask candidate(g, 0);
  for (std::size_t v = 0; v < candidate.voxels.size(); ++v) {
    const float d = depth_mm.voxels[v];
    candidate.voxels[v] = (d <= max_depth_mm || (thick && !near_cavity.voxels[v])) && d <= max_depth_mm + cap_mm &&
                          half_fluid_or_more(v);
  }
  const Mask body = fluid_bodies(candidate, max_depth_mm);
  Mask caps = caps_beyond_fluid(brain, ventricle, body, centre_voxel, max_depth_mm);
  if (thick) {
    // A thick cap's voxels are darker than the cortex can be: below the
    // midpoint of the cortex's class and the darkest major parenchyma class
    // (the white matter's), which never reaches the brain's surface. A
    // gyrus's crown over a sulcus's fluid is grey matter, brighter still in
    // partial volume with that fluid; taken as caps, crowns and the sulcal
    // fluid beneath them cost the T2-like resections 0.001-0.005 of Dice.
    const GaussianClass* darkest = cortex;
    for (const auto& c : classes)
      if (c.tissue == Tissue::parenchyma && c.weight >= kMajorClassWeight && c.mean < darkest->mean) darkest = &c;
    const double darker_than_cortex = 0.5 * (darkest->mean + cortex->mean);
    const Mask thick_caps = caps_beyond_fluid(brain, ventricle, body, centre_voxel, cap_mm);
    for (std::size_t v = 0; v < caps.voxels.size(); ++v)
      caps.voxels[v] = caps.voxels[v] || (thick_caps.voxels[v] && !near_cavity.voxels[v] &&
                                          image.voxels[v] / bias[v] < darker_than_cortex);
  }
  Mask uncapped = filled;
  for (std::size_t v = 0; v < uncapped.voxels.size(); ++v) uncapped.voxels[v] = filled.voxels[v] && !caps.voxels[v];

  // From the outside in through candidates within the rim's depth of the
  // outline without its caps: the face-connected pieces with a voxel next
  // to that outside.
  if (thick) {
    const ImageF rim_depth_mm = distance_to_mask_mm(complement(uncapped), max_depth_mm);
    for (std::size_t v = 0; v < candidate.voxels.size(); ++v)
      candidate.voxels[v] = rim_depth_mm.voxels[v] <= max_depth_mm && half_fluid_or_more(v);
  }
  int count = 0;
  const auto pieces = connected_components(candidate, 6, &count);
  std::vector<std::uint8_t> reached(static_cast<std::size_t>(count) + 1, 0);
  const Mask next_to_outside = boundary_voxels(uncapped);  // a face neighbour outside
  for (std::size_t v = 0; v < candidate.voxels.size(); ++v)
    if (candidate.voxels[v] && next_to_outside.voxels[v]) reached[pieces.voxels[v]] = 1;
  for (std::size_t v = 0; v < candidate.voxels.size(); ++v) rim.voxels[v] = reached[pieces.voxels[v]] || caps.voxels[v];
  return rim;
}

}  // namespace brainshift::segmentation
