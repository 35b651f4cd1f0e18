#pragma once
// The field beyond the brain must not pull preop tissue out of it
// (docs/DESIGN.md "The field beyond the brain"). Beyond the deformed mesh the
// pull-back is the affine plus the non-rigid remainder r faded with the
// distance d: w = 1 - smoothstep(d / blend_distance_mm). Where the brain sank
// by more than the fade's reach (a 25 mm sinking, a 10 mm fade), the voxels of
// the gap it left, air or fluid now, faded to the affine and pulled back into
// the preop brain that was there: the warped labels drew parenchyma (and a
// superficial tumour) up to 18 mm into the air, and any structure warped
// through the field in 3D Slicer would be drawn there too, a second image of
// the preop brain beside the one the mesh carries.
//
// The guard keeps the extension where the fade would do that: a voxel outside
// the mesh's image and outside the intraop brain outline whose pull-back lands
// in preop tissue takes the smallest weight in [w, 1] that lands it outside
// (the remainder continued as at the sunken surface carries the gap up to
// where the preop brain ended); the weights so raised are spread with a slope
// of 1 / blend_distance_mm, the fade's own scale, so that the field stays
// continuous. Outline voxels are never raised for their own landing (their
// tissue is the brain's), but take the spread weight of a neighbour so the
// field does not jump at the outline. Internal to the field module: the
// continuation (displacement_field.cpp) calls it on its box.
#include <Eigen/Dense>
#include <cstddef>
#include <vector>

#include "core/image.h"
#include "image/image_stats.h"

namespace brainshift {

// What pullback_field needs to guard the extension: the preop labels (tissue:
// any non-zero label, on their own grid, preop world mm), the box of their
// tissue (tissue_voxel_box, worked out once per preop) and the intraop brain
// outline (on the field's grid).
struct TissueGuard {
  const LabelImage* preop_labels = nullptr;
  VoxelBox preop_tissue_voxels;
  const Mask* intraop_outline = nullptr;
  // How far beyond the outline (and the mesh's image) a voxel's own landing
  // is not judged: the outline's own uncertainty, within which a voxel may
  // be brain the segmentation missed (a segmenter's partial-volume erosion)
  // and rightly pull back into preop tissue. Such voxels still take the
  // spread of a landing beyond it.
  double outline_tolerance_mm = 0.0;
};

struct TissueGuardStats {
  std::size_t raised_voxels = 0;         // voxels whose weight the guard raised (landing or spread)
  std::size_t landing_voxels = 0;        // voxels that landed in preop tissue under the fade
  std::size_t unresolved_voxels = 0;     // ... and still do with the whole remainder (weight 1)
};

// On one box of the field's grid: `covered`, `region` (covered + enclosed
// cavities) and `outline` are masks of the box; `rest` the non-rigid
// remainder (world mm) filled on every uncovered voxel outside the region;
// `weight` the fade's weights, raised in place. A voxel within
// outline_tolerance_mm of the outline or the region is not judged itself. The pull-back of a voxel x is
// A^-1 x + w r(x). Bounded work: one landing test per voxel, a bisection of
// 12 steps per landing voxel, two chamfer passes over the landing voxels' box
// grown by the blend distance.
TissueGuardStats guard_tissue(const Grid3& box_grid, const std::vector<std::uint8_t>& covered,
                              const std::vector<std::uint8_t>& region, const std::vector<std::uint8_t>& outline,
                              const std::vector<Eigen::Vector3f>& rest, const Eigen::Matrix4d& intraop_from_preop,
                              const LabelImage& preop_labels, double outline_tolerance_mm, double blend_distance_mm,
                              std::vector<float>& weight);

// The voxels of the labels' tissue (any non-zero label); empty when none.
VoxelBox tissue_voxel_box(const LabelImage& labels);

// The box (in voxels of `grid`) that holds the preop tissue's image under
// intraop_from_preop (tissue: its box on the preop grid): where a pull-back
// can land in it. Empty when there is no tissue or it maps off the grid.
VoxelBox preop_tissue_box(const VoxelBox& tissue, const Grid3& preop_grid, const Eigen::Matrix4d& intraop_from_preop,
                          const Grid3& grid);

}  // namespace brainshift
