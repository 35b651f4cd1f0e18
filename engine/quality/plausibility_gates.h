#pragma once
// Plausibility gates: is the input, and the answer made from it, physically
// possible for one patient between two scans of one operation? Every other
// quality figure measures agreement with the input (a leaking segmentation is
// matched beautifully); these measure the input and the result against what
// brain shift, head positioning and soft tissue allow.
//
// Each gate reports its value, its limit and pass/fail (metrics.json
// "plausibility", PROTOCOL.md); a failed gate turns the scan into the marked
// affine-only fallback with the gate's reason. The limits and why they are
// where they are: docs/DESIGN.md, "Plausibility gates".
#include <functional>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "core/image.h"
#include "core/tet_mesh.h"
#include "image/morphology.h"

namespace brainshift {

struct PlausibilityLimits {
  bool enabled = true;
  // |intraop brain (+ enclosed cavities) / (det A x preop brain) - 1|.
  double max_volume_change = 0.15;
  // Intraop over affine-mapped preop ventricle volume: CSF drainage halves
  // them at most; a ventricle label covering brain tissue multiplies them.
  double max_ventricle_volume_ratio = 3.0;
  // Principal stretches of the affine within [1/(1+d), 1+d] (scale and
  // shear), d along each principal direction = base + share x depth / extent:
  // what the scanner and the segmentation allow (base), plus the part of the
  // deepest plausible sink the affine absorbs, which grows as the brain seen
  // along that direction shortens (a slab, a short coil). DESIGN.md.
  double affine_stretch_base = 0.03;
  double affine_sink_share = 0.65;
  double max_sink_depth_mm = 25.0;
  // Rotation angle of the affine's rotation part.
  double max_head_rotation_deg = 90.0;
  // Left-right: a test prefers one side when its score beats the other's by
  // this much (label overlap, and squared image correlation).
  double left_right_overlap_margin = 0.05;
  double left_right_r2_margin = 0.02;
  // The field: largest non-rigid displacement anywhere and the RMS small
  // strain over the brain. (Motion beyond what the surface data ask for is
  // QualityGates::max_unsupported_displacement_mm's gate.)
  double max_displacement_mm = 40.0;
  double max_rms_strain = 0.20;
  // The warped preop T1 may not match the intraop image worse than the affine
  // alone by more than this (squared correlation): sub-voxel field changes
  // at the edges of a piecewise-constant image already cost 0.04 (measured).
  double image_r2_tolerance = 0.15;
};

struct GateResult {
  std::string name;        // "volume", "affine_stretch", ...
  bool tested = true;      // false: not applicable (reason in detail)
  bool passed = true;
  double value = 0;
  std::string limit;       // e.g. "<= 0.15"
  std::string detail;      // what the value is, or why untested
  nlohmann::json extra = nlohmann::json::object();
};

class PlausibilityReport {
 public:
  void add(GateResult g) { gates_.push_back(std::move(g)); }
  // "plausibility gate <name>: <detail> (value v, limit l)" of the first
  // failed gate; empty when all passed.
  std::string first_failure() const;
  nlohmann::json to_json() const;
  const std::vector<GateResult>& gates() const { return gates_; }

 private:
  std::vector<GateResult> gates_;
};

// The preop labels (any label) that intraop_from_preop places inside the
// intraop grid, sampled at every second voxel along each axis.
struct PreopInView {
  double fraction = 1.0;                            // of all labelled voxels
  std::vector<Eigen::Vector3f> points_preop_mm;     // the sampled voxels in view
  // Extent along a preop-frame unit direction: 1st to 99th percentile (mm).
  double extent_mm(const Eigen::Vector3d& direction_preop) const;
};
PreopInView preop_in_view(const LabelImage& preop, const Grid3& intraop, const Eigen::Matrix4d& intraop_from_preop);

// Brain volume: intraop outline (enclosed cavities filled) against the preop
// outline mapped by the affine. preop_in_view_ml: the part of the preop
// outline the affine places inside the intraop field of view (a slab or a
// short coil cuts the brain; the cut-off part is not missing tissue).
// open_fluid_ml: fluid the automatic segmentation found where the brain was
// (the gap a sinking leaves under the dura), counted with the brain: that
// volume was brain in the preop and the skull holds it; 0 for given labels.
GateResult volume_gate(double intraop_ml, double preop_in_view_ml, const Eigen::Matrix4d& intraop_from_preop,
                       const PlausibilityLimits& limits, double open_fluid_ml = 0.0);
// Lateral ventricles, the same way; untested when either side has none.
GateResult ventricle_volume_gate(double intraop_ml, double preop_ml, const Eigen::Matrix4d& intraop_from_preop,
                                 const PlausibilityLimits& limits);
// Principal stretches and rotation angle of the affine (polar decomposition).
// visible_extent_mm(v): the brain's extent in view along the preop-frame
// principal direction v (PreopInView::extent_mm), which sets that
// direction's limit.
using ExtentAlong = std::function<double(const Eigen::Vector3d& direction_preop)>;
// sink_gap_ml: the gap a sinking left under the dura that the automatic
// segmentation found in the image (IntraopInput::open_fluid_ml; 0 for given
// labels). With one, the most compressed principal direction is held to
// affine_sink_limit instead: the sink is seen, not inferred.
std::vector<GateResult> affine_gates(const Eigen::Matrix4d& intraop_from_preop, const PlausibilityLimits& limits,
                                     const ExtentAlong& visible_extent_mm, double sink_gap_ml = 0.0);
// The rigid part of an affine: the rotation of its polar decomposition
// L = R S, and the translation that puts centre_mm (preop frame) where the
// affine puts it. What a head can do between two scans.
Eigen::Matrix4d rigid_part(const Eigen::Matrix4d& intraop_from_preop, const Eigen::Vector3d& centre_mm);

// The gates that judge the geometry of the labels the affine was fitted to
// (volume, affine_stretch): when one refuses, the affine carries the
// labels' error (a lost lobe shrinks it, a leak inflates it) and the
// affine-only fallback delivers its rigid part instead (docs/DESIGN.md,
// "Quality gates").
bool refuses_labels_geometry(const PlausibilityReport& report);

// The stretch limit along a direction whose brain extent in view is extent_mm.
double affine_stretch_limit(double extent_mm, const PlausibilityLimits& limits);
// The same along the one direction a sinking the image shows compresses:
// the deepest sink the gates allow taken in full (share 1), the most an
// affine absorbs of a sink whose displacement falls linearly to zero across
// the brain seen (docs/DESIGN.md, affine_stretch).
double affine_sink_limit(double extent_mm, const PlausibilityLimits& limits);

// The solved non-rigid displacement at the mesh nodes: largest displacement
// and RMS small strain over the mesh volume.
std::vector<GateResult> field_gates(const TetMesh& preop_mesh, const std::vector<Eigen::Vector3d>& nonrigid_mm,
                                    const PlausibilityLimits& limits);

// Squared correlation of the intraop T1 with the preop T1 pulled back by the
// served field, against the same through the affine alone, over the intraop
// brain (sampled). Untested without an intraop image.
GateResult image_gate(const ImageF& preop_t1, const ImageF& intraop_t1, const Mask& intraop_brain,
                      const VectorImage3& pullback_field_mm, const Eigen::Matrix4d& intraop_from_preop,
                      const PlausibilityLimits& limits);

// Squared Pearson correlation of paired samples (0 when either is constant).
double squared_correlation(const std::vector<double>& a, const std::vector<double>& b);

}  // namespace brainshift
