#pragma once
// The head the classifier tests share (test_tissue_em.cpp, test_open_fluid.cpp):
// grey and white matter, ventricles, fluid around the brain, skull, scalp and
// air, a known smooth bias and Gaussian noise; optionally a fluid cavity or a
// cortex sunk under a craniotomy. And the measures the tests compare with.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>

#include <Eigen/Dense>

#include "core/image.h"
#include "field/metrics.h"
#include "segmentation/intraop_segmentation.h"
#include "segmentation/tissue_em.h"

namespace brainshift::segmentation::test_support {

struct Intensities {
  float wm = 100, gm = 70, ventricle = 25, fluid = 25, skull = 8, scalp = 75, air = 2;
};

struct Synthetic {
  ImageF image;
  LabelImage truth;   // 1 brain, 2 ventricles
  ImageF true_bias;
};

inline double ellipsoid(const Eigen::Vector3d& p, const Eigen::Vector3d& centre, const Eigen::Vector3d& semi) {
  return ((p - centre).array() / semi.array()).matrix().norm();
}

// Brain: ellipsoid (56, 66, 48 mm) with a 3 mm grey-matter rind and two deep
// grey nuclei; ventricles:
// two ellipsoids beside the midline; 3 mm of fluid, 5 mm of skull and 5 mm of
// scalp around it; air beyond. cavity_mm > 0: a fluid ball of that radius
// just under the brain's top (a resection). sink_mm > 0: the brain's top
// sunk under a craniotomy, by sink_mm at its centre falling to 0 at 35 mm
// from it; fluid fills the gap, and its top 3 mm, under the skull, are dura
// and inner-table partial volume as bright as grey matter.
inline Synthetic make_head(const Intensities& in, double noise_sd, double bias_amplitude, double cavity_mm = 0,
                    Eigen::Vector3d spacing = {1.2, 1.2, 2.0}, double sink_mm = 0) {
  Grid3 g;
  g.dims = {static_cast<int>(170 / spacing[0]), static_cast<int>(190 / spacing[1]), static_cast<int>(150 / spacing[2])};
  g.world_from_voxel.diagonal().head<3>() = spacing;
  g.world_from_voxel.block<3, 1>(0, 3) = -0.5 * Eigen::Vector3d(g.dims[0] * spacing[0], g.dims[1] * spacing[1], g.dims[2] * spacing[2]);
  Synthetic s{ImageF(g), LabelImage(g, 0), ImageF(g, 1.f)};
  const Eigen::Vector3d brain(56, 66, 48), c(0, 0, 0);
  std::mt19937 rng(7);
  std::normal_distribution<float> noise(0.f, static_cast<float>(noise_sd));
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d at = g.world_mm(i, j, k);
        // Tissue here came from sink down above it; the gap is where the
        // brain was and no longer is.
        // Falling off with depth, from the sunken surface (48 - sink_mm
        // above the centre) to the ventricles' top (16): deep structures
        // move little.
        const double lateral = std::max(0.0, 1 - at.head<2>().squaredNorm() / (35.0 * 35.0));
        const double dent = sink_mm * lateral * std::clamp((at.z() - 16) / (48 - sink_mm - 16), 0.0, 1.0);
        const Eigen::Vector3d p = at + Eigen::Vector3d(0, 0, dent);
        const double r = ellipsoid(p, c, brain);
        const double r_before = ellipsoid(at, c, brain);
        const bool gap = r >= 1 && r_before < 1 + 3.0 / 50;
        const double depth_mm = (1 - r) * 50;  // about mm below the brain surface
        // Deep grey matter (basal ganglia, thalami) beside the ventricles, as
        // in every brain: grey matter is not only a rind.
        const bool deep_grey = ellipsoid(p, {-22, 0, 0}, {8, 14, 10}) < 1 || ellipsoid(p, {22, 0, 0}, {8, 14, 10}) < 1;
        const bool vent = ellipsoid(p, {-9, 0, 8}, {6, 22, 8}) < 1 || ellipsoid(p, {9, 0, 8}, {6, 22, 8}) < 1;
        const bool cavity = cavity_mm > 0 && (p - Eigen::Vector3d(0, 10, 48 - cavity_mm + 2)).norm() < cavity_mm;
        float v;
        std::uint16_t label = 0;
        if (r < 1 && !cavity) {
          label = vent ? 2 : 1;
          v = vent ? in.ventricle : (depth_mm < 3 || deep_grey) ? in.gm : in.wm;
        } else if (gap) v = r_before > 1 - 3.0 / 50 && dent > 6 ? in.gm : in.fluid;
        else if (cavity || r_before < 1 + 3.0 / 50) v = in.fluid;  // the skull and scalp stay
        else if (r_before < 1 + 8.0 / 50) v = in.skull;
        else if (r_before < 1 + 13.0 / 50) v = in.scalp;
        else v = in.air;
        const Eigen::Vector3d q = at.array() / Eigen::Vector3d(85, 95, 75).array();
        const float b = static_cast<float>(std::exp(bias_amplitude * (0.8 * q.x() + 0.5 * q.y() * q.y() - 0.4 * q.z())));
        s.truth.at(i, j, k) = label;
        s.true_bias.at(i, j, k) = b;
        s.image.at(i, j, k) = std::max(0.f, b * v + noise(rng));
      }
  return s;
}

// Dice of one label of the two label maps (field/metrics.h).
inline double dice(const LabelImage& a, const LabelImage& b, std::uint16_t label) {
  return dice_per_label(a, b, {label}).front().dice;
}

inline const GaussianClass* nearest_class(const IntraopSegmentation& s, Tissue t, double value) {
  const GaussianClass* best = nullptr;
  for (const auto& g : s.classes)
    if (g.tissue == t && (!best || std::abs(g.mean - value) < std::abs(best->mean - value))) best = &g;
  return best;
}

inline SegmentationParameters params_for_test() {
  SegmentationParameters p;
  p.prior_width_mm = 3.0;
  return p;
}

}  // namespace brainshift::segmentation::test_support
