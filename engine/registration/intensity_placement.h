#pragma once
// The preop placed on an intraop image by its intensities, for a preop T1
// whose head the image-only path cannot use: a brain-extracted T1 (skull
// and scalp removed, as planning systems and atlases store them; the
// mricron-data ch2bet) has no head outline to match the scan's head to, and
// matching its brain to the scan's head shrank it onto the scalp
// (docs/DESIGN.md "A brain-extracted preop"). Here the preop T1's brain
// voxels are compared with the intraop image through a rigid transform and
// an isotropic scale: the squared normalised correlation (so that a T2-like
// scan, dark where the T1 is bright, places as well), on images smoothed to
// 4 then 2 mm, by a bounded pattern search from the start given. Rigid by
// default (IntensityPlacementParameters::max_log_scale).
#include <Eigen/Dense>
#include <string>
#include <vector>

#include "core/image.h"
#include "image/morphology.h"

namespace brainshift {

struct IntensityPlacementParameters {
  // Smoothing (Gaussian sigma) and sample spacing of the levels, coarse to
  // fine: 4 mm captures the centimetres a scanner's placement of the head
  // leaves; 2 mm places within about a millimetre, which the first
  // segmentation round's 3 mm prior needs.
  double coarse_mm = 4.0, fine_mm = 2.0;
  std::size_t max_samples = 40000;  // per level, a strided subset of the brain's voxels
  int max_evaluations = 600;        // per level (bounded search)
  // Steps at the start (translation mm, rotation deg, log scale; the fine
  // level starts at half); the search halves them down to 1/finest_step_fraction
  // (0.125 mm and 0.125 deg: a tenth of the fine level's 2 mm, below what
  // the first round's 3 mm prior can feel).
  double translation_step_mm = 4.0, rotation_step_deg = 4.0, log_scale_step = 0.04;
  double finest_step_fraction = 32.0;
  // The isotropic scale's bound, |log scale|. 0 (the default): rigid. The
  // preop and the scan are the same patient's brain, and with a scale the
  // fit shrank the preop into the gap a 20 mm sinking leaves (volume -13 %,
  // refused by the segmentation's volume gate; docs/performance/12.45).
  double max_log_scale = 0.0;
  // The pose search (search_pose_by_intensity): the head's yaw about the
  // preop's S-I axis every pose_yaw_step_deg all round, and its pitch and
  // roll 0 and +-pose_tilt_deg, each candidate's translation searched on the
  // coarse level (steps 8 mm down to 2 mm, at most pose_evaluations) with at
  // most pose_samples samples. Surgery positions the head in its clamp
  // turned up to 90 degrees for a lateral approach, flexed or tilted by
  // tens of degrees, and a prone patient recorded as supine turns it 180:
  // the scanner's RAS does not follow any of it. 30 degree steps leave any
  // pose within 15 degrees of yaw (and of pitch and roll up to 45) of a
  // candidate, inside the placement's own reach from it (its 4 degree
  // steps, on a 4 mm blur of a 140 mm brain).
  double pose_yaw_step_deg = 30.0, pose_tilt_deg = 30.0;
  std::size_t pose_samples = 2000;  // r's sampling error ~(1 - r^2) / sqrt(n) ~ 0.01, against 0.2-0.7 between poses
  int pose_evaluations = 40;
};

struct IntensityPlacement {
  Eigen::Matrix4d intraop_from_preop = Eigen::Matrix4d::Identity();
  double correlation = 0;      // normalised correlation at the end (signed)
  double inside_fraction = 0;  // of the samples, mapped inside the image
  int evaluations = 0;
  std::string message;
};

// What the placement compares of the preop, per level: its brain's voxels
// (strided at the level's spacing, at most max_samples) in preop world mm
// and the T1 smoothed to the level there. The same for every scan of a
// preop, so the daemon makes it once (WarmState): smoothing the 1 mm T1
// twice cost 0.7 s a scan.
struct IntensityPlacementPreop {
  struct Level {
    double smoothing_mm = 0;
    std::vector<Eigen::Vector3f> at_mm;
    std::vector<float> value;
  };
  Eigen::Vector3d centre_mm = Eigen::Vector3d::Zero();  // the brain's centroid, the rotations' centre
  std::vector<Level> levels;                            // coarse to fine
};

// preop_brain: the preop voxels to compare (the brain labels), on the T1's
// grid. InputError for an empty brain or grids that differ.
IntensityPlacementPreop intensity_placement_preop(const ImageF& preop_t1, const Mask& preop_brain,
                                                  const IntensityPlacementParameters& p = {});

// What the placement reads of the scan, per level of the preop's: the scan
// smoothed to the level, on a grid of the level's spacing. Made once per scan
// and shared by every step that compares it (a first scan of a turned head
// correlates, searches and places: five smoothings of the scan otherwise).
struct IntensityPlacementScan {
  std::vector<ImageF> levels;  // as IntensityPlacementPreop::levels
};
IntensityPlacementScan intensity_placement_scan(const IntensityPlacementPreop& preop, const ImageF& intraop);

IntensityPlacement place_by_intensity(const IntensityPlacementPreop& preop, const IntensityPlacementScan& intraop,
                                      const Eigen::Matrix4d& start_intraop_from_preop,
                                      const IntensityPlacementParameters& p = {});

// The normalised correlation at a placement, on the fine level (signed).
double intensity_correlation(const IntensityPlacementPreop& preop, const IntensityPlacementScan& intraop,
                             const Eigen::Matrix4d& intraop_from_preop, const IntensityPlacementParameters& p = {});

// The head's pose found by intensity whatever it is (the candidates above,
// about the preop brain's centre after start): the best candidate, for
// place_by_intensity to refine. 108 candidates of at most 41 evaluations on
// 2000 samples.
struct PoseSearch {
  Eigen::Matrix4d intraop_from_preop = Eigen::Matrix4d::Identity();
  double correlation = 0;              // the coarse level's, on the thinned samples
  double rotation_from_start_deg = 0;  // of the best candidate
  int candidates = 0, evaluations = 0;
  double seconds = 0;
};
PoseSearch search_pose_by_intensity(const IntensityPlacementPreop& preop, const IntensityPlacementScan& intraop,
                                    const Eigen::Matrix4d& start, const IntensityPlacementParameters& p = {});

// Both steps at once.
IntensityPlacement place_by_intensity(const ImageF& preop_t1, const Mask& preop_brain, const ImageF& intraop,
                                      const Eigen::Matrix4d& start_intraop_from_preop,
                                      const IntensityPlacementParameters& p = {});

}  // namespace brainshift
