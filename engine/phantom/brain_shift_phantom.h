#pragma once
// Synthetic intraoperative test cases with a known answer, made from a preop
// T1 and its label map. The deformation is an analytic, smooth, invertible map
// that has nothing to do with the engine's elastic model, so a registration
// can be judged against it without grading its own physics.
//
// The truth is built as a FORWARD map in the preop frame, composed of
//   midline shift -> sinking under a craniotomy -> swelling -> collapse toward
//   a resection -> retractor dent,
// each of the form p -> p + f(p) with |grad f| < 1, or a displacement along
// one fixed direction whose derivative along that direction is > -1 (the
// sinking, the shift and the dent; their inverse is then a 1-D contraction),
// hence a diffeomorphism,
// followed by a rigid head repositioning M (intraop_from_preop). The pull-back
// field on the intraop grid, u(x) = phi^-1(x) - x (engine/core/deformation.h),
// is obtained by undoing M and then inverting each component by fixed-point
// iteration, to well below 1e-3 mm. The Jacobian determinant of x -> x + u(x)
// is measured on the grid (finite differences); if it drops below
// min_jacobian anywhere the non-rigid amplitudes are scaled down (recorded in
// the description).
//
// Images: intraop T1 = preop T1 at x + u(x) (trilinear) where that point is
// brain tissue. Tissue outside the brain (skull, scalp) does not follow the
// brain: it is sampled through the rigid move only, and where the brain has
// pulled away from it (the gap under the craniotomy) or was resected the voxel
// gets a dark fluid intensity. Then a smooth multiplicative bias field and
// Rician noise. Intraop labels (1 brain incl. everything inside it except the
// ventricles, 2 lateral ventricles, 0 elsewhere and in the resection cavity)
// come from the preop signed distance maps at x + u(x), thresholded after
// adding a smooth random field (about noise_mm RMS, correlation length
// label_noise_correlation_mm): segmentation noise that is spatially
// correlated like a real one.
// Everything is deterministic for a given seed.
//
// Where: the deformation in phantom_deformation.cpp, the images in
// brain_shift_phantom.cpp, the artefacts in phantom_artefacts.h, the standard
// suite in phantom_presets.cpp.
#include <Eigen/Dense>
#include <cstdint>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/image.h"
#include "phantom/tumor_implant.h"

namespace brainshift {

struct SinkingSpec {
  bool enabled = true;
  // Craniotomy site: the brain surface point hit by a ray from the brain
  // centroid along this direction (preop RAS, need not be unit).
  Eigen::Vector3d craniotomy_direction{-0.5, 0.7, 0.5};
  // Gravity in the preop frame; empty = straight into the brain (minus the
  // outward surface direction at the craniotomy). Must point into the brain.
  std::optional<Eigen::Vector3d> gravity;
  double cortex_mm = 12;         // displacement of the cortex under the craniotomy
  double deep_mm = 2;            // displacement of deep structures (tapers to 0 at the far side)
  double depth_decay_mm = 30;    // Gaussian decay length of (cortex - deep) with depth
  double lateral_radius_mm = 45; // Gaussian fade with distance from the gravity axis
};

struct SwellingSpec {
  bool enabled = false;
  // Centre as an offset from the brain centroid (preop mm).
  Eigen::Vector3d centre_offset_mm{20, 10, 20};
  double amplitude_mm = 3;   // peak radial outward displacement
  double radius_mm = 25;     // where the peak is reached
};

struct ResectionSpec {
  bool enabled = false;
  // The resected region: the tumour label when present in the preop labels,
  // else a ball below the craniotomy (or at the offset from the brain centroid
  // when sinking is disabled).
  std::uint16_t tumor_label = 4;
  double ball_radius_mm = 12;
  double ball_depth_mm = 20;  // depth of the ball centre below the craniotomy point
  Eigen::Vector3d centre_offset_mm{0, 30, 20};
  double collapse_mm = 4;     // inward displacement of the cavity wall (< cavity radius)
  double collapse_decay_mm = 15;
  // Partial resection: the part of the region nearest the surface (along
  // -gravity, or away from the brain centroid without sinking) is removed,
  // this fraction of its extent; the rest stays as tissue.
  double resected_fraction = 1;
  // Blood settled in the cavity: its dependent part (along gravity), this
  // fraction of the cavity's extent; T1 of blood relative to the brain's
  // median (methaemoglobin: intermediate to bright). Used by the intraop
  // scene (intraop_scene.h); make_phantom fills the cavity with fluid.
  double blood_fill_fraction = 0;
  double blood_t1_relative = 1.1;
};

// A retractor blade pressed into the cortex after the brain has sunk: a dent
// of depth_mm along the push direction under a blade of half_length_mm along
// its long axis (flat, then a Gaussian edge of half_width_mm) and
// half_width_mm across (Gaussian), fading (Gaussian) with depth below the
// dented surface. The lateral gradient is steep (7 mm over 3 mm): it only
// shears, the Jacobian is 1 + d(dent)/d(depth) > 0.
struct RetractorSpec {
  bool enabled = false;
  Eigen::Vector3d offset_mm{0, 0, 0};  // blade centre: the sunken craniotomy point + this
  std::optional<Eigen::Vector3d> push; // empty: into the brain (minus the craniotomy direction)
  double blade_angle_deg = 0;          // long axis, rotated about the push in its normal plane
  double depth_mm = 7;
  double half_length_mm = 12;
  double half_width_mm = 3;
  double depth_decay_mm = 12;
};

// Midline shift (subfalcine, from mass effect): deep structures pushed
// across the midline, amplitude_mm at the centre, Gaussian of radius_mm.
struct MidlineShiftSpec {
  bool enabled = false;
  Eigen::Vector3d centre_offset_mm{0, 0, 10};  // from the brain centroid (the ventricles' depth)
  Eigen::Vector3d direction{1, 0, 0};
  double amplitude_mm = 4;
  double radius_mm = 30;
};

struct RigidSpec {
  Eigen::Vector3d rotation_deg{0, 0, 0};  // about R, A, S axes through the brain centroid
  Eigen::Vector3d translation_mm{0, 0, 0};
};

struct PhantomSpec {
  std::string name = "phantom";
  std::uint64_t seed = 1;
  SinkingSpec sinking;
  SwellingSpec swelling;
  ResectionSpec resection;
  RetractorSpec retractor;
  MidlineShiftSpec midline_shift;
  RigidSpec rigid;
  // Intraop (iMRI-like) grid, centred on the moved brain centroid plus
  // grid_centre_offset_mm (world RAS+ mm; a short coil over the craniotomy
  // sees the top of the head and misses the base).
  std::array<int, 3> dims{256, 256, 60};
  Eigen::Vector3d grid_centre_offset_mm{0, 0, 0};
  Eigen::Vector3d spacing_mm{0.9375, 0.9375, 2.5};
  Eigen::Vector3d oblique_deg{0, 0, 0};  // rotation of the grid axes (R, A, S)
  bool flip_first_axis = false;          // handedness-flipping voxel order
  // Image degradation.
  double bias_amplitude = 0.15;    // multiplicative field within about 1 +- this
  double noise_fraction = 0.03;    // Rician sigma / 99th percentile of the brain intensity
  double label_noise_mm = 0.8;     // RMS boundary displacement of the segmentations
  double label_noise_correlation_mm = 10;
  std::size_t landmark_count = 200;
  double min_jacobian = 0.2;
  // Preop labels forming the brain and the lateral ventricles.
  std::vector<std::uint16_t> brain_labels{1, 2, 3, 4};
  std::uint16_t ventricle_label = 2;
  // Landmarks are weighted toward this label too (corticospinal tract).
  std::uint16_t tract_label = 3;
  // A tumor put into the preop before the case is made (implant_tumor): the
  // case must then be registered against that preop, not the plain atlas.
  // A resection case resects the tumor label when the preop has one.
  std::optional<TumorImplantSpec> preop_tumor;
};

struct PhantomCase {
  ImageF intraop_t1;
  LabelImage intraop_labels;
  VectorImage3 true_pullback_mm;  // u(x): x + u(x) = the matching preop point
  // (intraop point, true preop point), world RAS mm.
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> landmarks_intraop_preop_mm;
  Eigen::Matrix4d true_intraop_from_preop_rigid = Eigen::Matrix4d::Identity();
  nlohmann::json description;  // spec, derived points, scale factor, min Jacobian, timings
};

// InputError when the images are empty or disagree, no brain label is
// present, the craniotomy ray never leaves the brain, gravity points out of
// the brain, or a spec value is out of range.
PhantomCase make_phantom(const ImageF& preop_t1, const LabelImage& preop_labels, const PhantomSpec& spec);

// Six or more varied named cases (craniotomy sites, gravity, amplitudes,
// swelling, resection, rigid moves, obliquity, noise).
std::vector<PhantomSpec> standard_phantom_suite();

// The analytic truth without images: useful for tests and for evaluating a
// field at arbitrary points. Built once per spec and preop brain.
class PhantomDeformation {
 public:
  PhantomDeformation(const LabelImage& preop_labels, const PhantomSpec& spec);
  // phi: preop -> intraop (world mm).
  Eigen::Vector3d forward(const Eigen::Vector3d& preop_mm) const;
  // phi^-1: intraop -> preop.
  Eigen::Vector3d inverse(const Eigen::Vector3d& intraop_mm) const;
  // Multiplies every non-rigid amplitude (used to keep the Jacobian bounded).
  void scale_nonrigid(double factor);
  double nonrigid_scale() const { return scale_; }
  const Eigen::Matrix4d& intraop_from_preop_rigid() const { return rigid_; }
  const Eigen::Vector3d& brain_centroid_mm() const { return centroid_; }
  const Eigen::Vector3d& craniotomy_mm() const { return craniotomy_; }
  const Eigen::Vector3d& gravity() const { return gravity_; }
  const Eigen::Vector3d& resection_centre_mm() const { return resection_centre_; }
  double brain_depth_along_gravity_mm() const { return brain_depth_mm_; }
  double resection_radius_mm() const { return resection_radius_; }
  bool resection_uses_tumor_label() const { return resection_uses_label_; }
  // Signed distance (mm) to the cut of a partial resection, negative on the
  // resected side (-1e9 everywhere for a complete one). The cavity is the
  // resected region intersected with that side.
  double resection_cut_mm(const Eigen::Vector3d& preop_mm) const;
  const Eigen::Vector3d& retractor_centre_mm() const { return retractor_centre_; }

 private:
  Eigen::Vector3d sink(const Eigen::Vector3d& p) const;
  Eigen::Vector3d swell(const Eigen::Vector3d& p) const;
  Eigen::Vector3d collapse(const Eigen::Vector3d& p) const;
  Eigen::Vector3d retract(const Eigen::Vector3d& p) const;
  Eigen::Vector3d shift(const Eigen::Vector3d& p) const;
  void place_retractor();
  template <class F>
  static Eigen::Vector3d invert_component(const Eigen::Vector3d& y, F&& f);

  PhantomSpec spec_;
  double scale_ = 1;
  Eigen::Matrix4d rigid_ = Eigen::Matrix4d::Identity();
  Eigen::Matrix4d rigid_inverse_ = Eigen::Matrix4d::Identity();
  Eigen::Vector3d centroid_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d craniotomy_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d gravity_ = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d swelling_centre_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d resection_centre_ = Eigen::Vector3d::Zero();
  double resection_radius_ = 0;
  Eigen::Vector3d resection_up_ = Eigen::Vector3d::UnitZ();  // toward the surface
  Eigen::Vector3d retractor_centre_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d retractor_push_ = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d retractor_long_ = Eigen::Vector3d::UnitX();
  Eigen::Vector3d retractor_across_ = Eigen::Vector3d::UnitY();
  double brain_depth_mm_ = 100;  // brain extent along gravity from the craniotomy
  bool resection_uses_label_ = false;
};

// Min Jacobian determinant of x -> x + u(x) over the grid (central
// differences in world mm, one-sided at the border).
double min_jacobian_determinant(const VectorImage3& pullback_mm);

}  // namespace brainshift
