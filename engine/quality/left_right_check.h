#pragma once
// Left-right: a scan mirrored by an orientation error in a conversion (a
// flipped axis, LPS read as RAS) has a brain outline the affine fits about as
// well as the true one, and the surface match then drives a confident field
// with every lateral structure on the wrong side. A mirror is no motion: the
// affine cannot produce it (its determinant stays positive), so it has to be
// tested for. The asymmetric structures (ventricles, tumour) and the T1 when
// both scans have one are compared with the preop through the affine, and
// with the preop's mirror image (mirrored about its own mid-sagittal plane)
// through the same affine; a scan that fits the mirror better is refused.
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "quality/plausibility_gates.h"

namespace brainshift {

// What the gate needs of the preop alone (its mirror, each structure's voxel
// centres): the same for every scan of that preop, so the warm state makes
// it once (about 25 ms a scan on the default atlas otherwise).
struct LeftRightPreop {
  std::vector<std::pair<std::string, std::uint16_t>> structures;  // those the points are of
  Eigen::Matrix4d mirror = Eigen::Matrix4d::Identity();          // preop_mirror
  std::vector<std::vector<Eigen::Vector3d>> points_mm;           // per structure, preop world
};
LeftRightPreop left_right_preop(const LabelImage& preop_labels,
                                const std::vector<std::pair<std::string, std::uint16_t>>& structures);

struct LeftRightInput {
  const LabelImage& preop_labels;
  const LabelImage& intraop_labels;
  Eigen::Matrix4d intraop_from_preop;
  // The label structures tested (name, value): the asymmetric ones.
  std::vector<std::pair<std::string, std::uint16_t>> structures;
  const ImageF* preop_t1 = nullptr;    // both images or neither
  const ImageF* intraop_t1 = nullptr;
  const Mask* intraop_brain = nullptr; // where the images are compared
  // Made before from preop_labels (left_right_preop); used when made for
  // the same structures, else the gate makes its own.
  const LeftRightPreop* preop_side = nullptr;
};

// The preop's mirror about the plane x = (centroid of its labelled voxels).x,
// in preop world mm (RAS: x is left-right).
Eigen::Matrix4d preop_mirror(const LabelImage& preop_labels);

// value: tests preferring the mirror minus tests preferring the scan as
// given; fails when positive. Each test's scores are in the gate's extra.
GateResult left_right_gate(const LeftRightInput& in, const PlausibilityLimits& limits);

}  // namespace brainshift
