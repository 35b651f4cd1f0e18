#pragma once
// What the affine registration needs from each label map, computed once:
//   preop  : points on the structure boundaries + the moments of the outline;
//   intraop: signed distance maps of the same structures + moments.
// Split out so the pipeline can prepare the preop side offline (the atlas does
// not change between scans) and reuse the intraop distance maps for the
// active-surface stage.
#include <cstdint>
#include <vector>

#include <Eigen/Dense>

#include "core/image.h"
#include "image/morphology.h"

namespace brainshift {

// Zeroth, first and second moments of a mask in world mm.
struct MaskMoments {
  double volume_ml = 0;
  Eigen::Vector3d centroid_mm = Eigen::Vector3d::Zero();
  Eigen::Matrix3d covariance_mm2 = Eigen::Matrix3d::Zero();
};
MaskMoments mask_moments(const Mask& mask);

// Points on the boundary of a mask: the centre of every face shared by a
// foreground voxel and a 6-neighbour background voxel (the same place the zero
// level of signed_distance_mm lies). Faces on the image border are skipped: a
// mask cut by the field of view has no real surface there. The order is a fixed
// pseudo-random permutation (seeded), so any prefix is a spatially uniform,
// reproducible subsample.
std::vector<Eigen::Vector3d> mask_boundary_points_mm(const Mask& mask);

// The outline of the brain: every non-zero label (parenchyma, ventricles, tract,
// tumour all lie inside it) with internal holes filled.
Mask outline_mask(const LabelImage& labels);

struct PreopBoundarySamples {
  std::vector<Eigen::Vector3d> outer_mm;      // outline surface (brain + ventricles + ...)
  std::vector<Eigen::Vector3d> ventricle_mm;  // ventricle wall; empty when there are none
  MaskMoments outer_moments;
};
// Throws InputError when brain_label is absent.
PreopBoundarySamples prepare_preop_samples(const LabelImage& preop_labels,
                                           std::uint16_t brain_label, std::uint16_t ventricle_label);

struct IntraopDistanceMaps {
  ImageF outer_sdf_mm;      // signed distance to the outline (negative inside)
  ImageF ventricle_sdf_mm;  // signed distance to the ventricles; voxels empty when none
  MaskMoments outer_moments;
};
// The outline here is all non-zero labels with enclosed holes filled (an
// internal resection cavity is not outer surface). Throws InputError when
// brain_label is absent.
IntraopDistanceMaps prepare_intraop_maps(const LabelImage& intraop_labels,
                                         std::uint16_t brain_label, std::uint16_t ventricle_label);
// The same with the outline already computed (outline_mask of the labels), so
// a caller that needs it too computes it once.
IntraopDistanceMaps prepare_intraop_maps(const LabelImage& intraop_labels, const Mask& outline,
                                         std::uint16_t brain_label, std::uint16_t ventricle_label);

}  // namespace brainshift
