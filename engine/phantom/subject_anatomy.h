#pragma once
// Other heads: a new subject's preop T1 and labels made by warping an atlas
// (the default Colin27 atlas) through a smooth invertible map, so that a
// suite is not graded on the one anatomy the engine was developed on.
//
// The subject-from-atlas map psi is a composition of steps applied in order
//   ventricle enlargement -> tumour mass effect -> smooth reshaping -> scale,
// each step p -> p + f(p) with a Lipschitz constant of f below 1/2 (checked
// numerically where it is not analytic), so every step is a diffeomorphism
// whose inverse is a fixed-point iteration, and so is psi:
// - ventricle enlargement: the lateral ventricles grow (volume x factor) and
//   the tissue around moves with them. Velocity: the gradient of the
//   ventricles' smoothed signed distance (outward normal), full inside and at
//   the wall, Gaussian decay with the distance into the tissue; integrated
//   in K Euler steps (K from the measured gradient), amplitude found by
//   bisection on the volume the forward map gives the ventricles;
// - tumour mass effect: a radial push from a centre beside a ventricle
//   (peaking push_mm at radius_mm, Gaussian beyond), integrated in K steps:
//   the near ventricle wall moves more than the far one, so the ventricle is
//   compressed; the tumour is then implanted at the centre (tumor_implant.h);
// - reshaping: a few Gaussian RBF displacements (random centres in the brain,
//   random directions), one step each;
// - per-axis scale about the brain centroid.
// The subject's images are the atlas's sampled at psi^-1 (computed on a 2 mm
// lattice and interpolated: the subject IS these images; the analytic pair
// forward/inverse is what the tests check).
#include <Eigen/Dense>
#include <cstdint>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "phantom/tumor_implant.h"

namespace brainshift {

struct MassEffectSpec {
  Eigen::Vector3d side{-1, 0.2, 0};  // the tumour's side of the ventricles
  double gap_mm = 7;                 // tumour centre beyond the ventricles' outermost voxel on that side
  double radius_mm = 9;              // where the push peaks; also the implanted tumour's radius
  double push_mm = 6;
  double lobulation = 0.15;
  double intensity_fraction = 0.6;   // tumour T1 / brain median (hypointense)
  double cyst_radius_fraction = 0;   // a fluid core (TumorImplantSpec)
};

struct SubjectSpec {
  std::string name = "atlas";
  std::uint64_t seed = 1;
  Eigen::Vector3d axis_scale{1, 1, 1};  // R, A, S about the brain centroid
  int reshape_bumps = 0;
  double reshape_amplitude_mm = 4;      // peak of each bump (0.5-1 x this, random)
  double reshape_width_mm = 30;         // Gaussian sigma of each bump
  double ventricle_volume_factor = 1;   // 1: unchanged
  double ventricle_decay_mm = 12;       // how far into the tissue the enlargement reaches
  std::optional<MassEffectSpec> mass_effect;
  // A tumour implanted after the warp (e.g. the target of a resection).
  // Not together with mass_effect (one tumour label per subject).
  std::optional<TumorImplantSpec> tumor;
  std::vector<std::uint16_t> brain_labels{1, 2, 3, 4};
  std::uint16_t ventricle_label = 2;
  std::uint16_t tumor_label = 4;
};

// psi and its inverse, built from the atlas labels.
class SubjectWarp {
 public:
  SubjectWarp(const LabelImage& atlas_labels, const SubjectSpec& spec);
  Eigen::Vector3d forward(const Eigen::Vector3d& atlas_mm) const;   // atlas -> subject
  Eigen::Vector3d inverse(const Eigen::Vector3d& subject_mm) const; // subject -> atlas
  // Where the mass-effect tumour goes (subject frame); NaN without one.
  Eigen::Vector3d tumor_centre_mm() const;
  nlohmann::json description() const { return description_; }

 private:
  using Step = std::function<Eigen::Vector3d(const Eigen::Vector3d&)>;
  void add_ventricle_enlargement(const LabelImage& labels);
  void add_mass_effect(const LabelImage& labels);
  void add_reshaping(const LabelImage& labels);
  static Eigen::Vector3d invert_step(const Step& f, const Eigen::Vector3d& y);

  SubjectSpec spec_;
  std::vector<Step> steps_;  // applied in order before the scale
  Eigen::Vector3d centroid_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d mass_centre_ = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  std::size_t push_end_ = 0;  // steps after the mass effect's push
  nlohmann::json description_ = nlohmann::json::object();
};

struct Subject {
  std::string name;
  ImageF t1;          // on the atlas's grid
  LabelImage labels;  // same grid
  nlohmann::json description;  // spec, ventricle volumes, tumour, timings
};

// InputError on a bad spec (scale outside 0.8-1.25, volume factor outside
// 0.5-4, both a tumour and a mass effect) or atlas images that disagree.
Subject make_subject(const ImageF& atlas_t1, const LabelImage& atlas_labels, const SubjectSpec& spec);

}  // namespace brainshift
