#pragma once
// Label maps of heads other than the atlas, made from it by small
// deterministic operations (no randomness beyond a seeded std::mt19937, whose
// output the standard fixes): for the meshing tests and the warm-up bench.
// The shapes a hospital sees that the atlas is not: other proportions,
// enlarged ventricles, ventricles compressed by a tumour's mass effect, a
// tumour at the ventricle wall or at the brain surface, specks of mask noise.
#include <cstdint>
#include <string>
#include <vector>

#include "core/image.h"
#include "core/label_table.h"

namespace brainshift::test {

// The label values the shapes are painted with, from the label table.
struct HeadLabels {
  std::uint16_t brain = 0, ventricles = 0, tumour = 0;
};
HeadLabels head_labels_of(const LabelTable& table);

// Centroid (world mm) of the voxels with `label`; InputError when none.
Eigen::Vector3d label_centroid_mm(const LabelImage& labels, std::uint16_t label);

// A head of other proportions: scaled by `scale` per axis about the brain's
// centroid, then smoothly reshaped by a displacement of at most `bump_mm` per
// axis (one sine period over 120 mm, phases from `seed`: gradient at most
// 2 pi bump / 120, so the map stays one-to-one for bump < 19 mm).
LabelImage reshape_head(const LabelImage& labels, const HeadLabels& l, const Eigen::Vector3d& scale,
                        double bump_mm, unsigned seed);

// Ventricles grown inside the brain, nearest voxels first (a ball dilation
// stopped at the voxel count), to volume_factor times the original volume.
LabelImage enlarge_ventricles(const LabelImage& labels, const HeadLabels& l, double volume_factor);

// A spherical tumour of radius_mm at centre_mm whose mass effect pushes the
// tissue radially outward, preserving volume ((r^3 + R^3)^(1/3)): a ventricle
// next to it is compressed. The tumour overwrites whatever it covers.
LabelImage add_tumour_with_mass_effect(const LabelImage& labels, const HeadLabels& l,
                                       const Eigen::Vector3d& centre_mm, double radius_mm);

// The ventricles collapsed by a mass effect: the lost_fraction of their
// voxels nearest to centre_mm become brain (CSF is pressed out, tissue is
// incompressible: a volume-preserving push alone would not shrink them).
LabelImage collapse_ventricles_near(const LabelImage& labels, const HeadLabels& l, const Eigen::Vector3d& centre_mm,
                                    double lost_fraction);

// The point on the ray from `from_mm` along `direction` where the distance to
// the voxels with `label` (outside them) first reaches distance_mm; samples
// every 0.5 mm up to 150 mm. InputError when it is never reached.
Eigen::Vector3d point_at_distance_from_label(const LabelImage& labels, std::uint16_t label,
                                             const Eigen::Vector3d& from_mm, const Eigen::Vector3d& direction,
                                             double distance_mm);

// `count` specks of 1-2 voxels: brain label outside the brain (mask noise),
// ventricle label inside the brain, tumour label anywhere in the head's box.
LabelImage add_specks(const LabelImage& labels, const HeadLabels& l, int count, unsigned seed);

// A named head for the tests and the bench (see head_shapes.cpp for each).
struct HeadCase {
  std::string name;
  LabelImage labels;
};
// The names: "atlas", "enlarged_ventricles_x1.8", "enlarged_ventricles_x2.4",
// "compressed_ventricles", "reshaped", "reshaped_compressed" (the kind of map
// that once made exudation run away), "tumour_at_ventricle_wall",
// "tumour_at_surface", "specks".
std::vector<std::string> head_case_names();
HeadCase make_head_case(const std::string& name, const LabelImage& atlas, const HeadLabels& l);

}  // namespace brainshift::test
