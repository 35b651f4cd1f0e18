#include "registration/intensity_placement.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/pose_sweep.h"
#include "core/rotation_angle.h"
#include "core/timer.h"
#include "image/gaussian_smooth.h"
#include "image/interpolation.h"
#include "image/resample.h"
#include "registration/boundary_samples.h"

namespace brainshift {
namespace {

constexpr double kPi = 3.14159265358979323846;

ImageF smoothed(const ImageF& image, double sigma_mm) {
  ImageF out = image;
  gaussian_smooth_voxels(out, Eigen::Vector3d(sigma_mm / image.grid.spacing_mm().array()));
  return out;
}

// Parameters: translation (mm), rotation (rad, about x, y, z), log scale;
// about the preop brain's centroid, after the start transform.
using Params = std::array<double, 7>;

Eigen::Matrix4d transform_of(const Params& q, const Eigen::Vector3d& centre, const Eigen::Matrix4d& start) {
  const Eigen::Matrix3d r = (Eigen::AngleAxisd(q[5], Eigen::Vector3d::UnitZ()) *
                             Eigen::AngleAxisd(q[4], Eigen::Vector3d::UnitY()) *
                             Eigen::AngleAxisd(q[3], Eigen::Vector3d::UnitX()))
                                .toRotationMatrix();
  Eigen::Matrix4d local = Eigen::Matrix4d::Identity();
  local.topLeftCorner<3, 3>() = std::exp(q[6]) * r;
  local.topRightCorner<3, 1>() = centre + Eigen::Vector3d(q[0], q[1], q[2]) - local.topLeftCorner<3, 3>() * centre;
  return start * local;
}

IntensityPlacementPreop::Level level_samples(const ImageF& preop, const Mask& brain, double spacing_mm,
                                             std::size_t max_samples) {
  const Eigen::Vector3d sp = preop.grid.spacing_mm();
  std::array<int, 3> stride;
  for (int a = 0; a < 3; ++a) stride[a] = std::max(1, static_cast<int>(std::lround(spacing_mm / sp[a])));
  IntensityPlacementPreop::Level s;
  s.smoothing_mm = spacing_mm;
  for (int k = 0; k < preop.grid.dims[2]; k += stride[2])
    for (int j = 0; j < preop.grid.dims[1]; j += stride[1])
      for (int i = 0; i < preop.grid.dims[0]; i += stride[0])
        if (brain.at(i, j, k)) {
          s.at_mm.push_back(preop.grid.world_mm(i, j, k).cast<float>());
          s.value.push_back(preop.at(i, j, k));
        }
  if (s.at_mm.size() > max_samples) {  // an even subset
    const double step = static_cast<double>(s.at_mm.size()) / static_cast<double>(max_samples);
    IntensityPlacementPreop::Level kept;
    kept.smoothing_mm = spacing_mm;
    for (std::size_t n = 0; n < max_samples; ++n) {
      const auto idx = static_cast<std::size_t>(static_cast<double>(n) * step);
      kept.at_mm.push_back(s.at_mm[idx]);
      kept.value.push_back(s.value[idx]);
    }
    return kept;
  }
  return s;
}

// The scan smoothed to the level and sampled on a grid of the level's
// spacing along every finer axis: a Gaussian of sigma h keeps 0.7 % of the
// amplitude at the Nyquist frequency of spacing h, so nothing aliases, and
// the search's hundreds of evaluations read an image that fits the cache (a
// 1 mm scan's 25 MB did not: 3 ms an evaluation, most of it waiting on
// memory).
ImageF scan_at_level(const ImageF& intraop, double level_mm) {
  const ImageF fine = smoothed(intraop, level_mm);
  std::array<int, 3> dims = intraop.grid.dims;
  const Eigen::Vector3d sp = intraop.grid.spacing_mm();
  for (int a = 0; a < 3; ++a)
    if (sp[a] < level_mm) dims[a] = std::max(2, static_cast<int>(std::lround(dims[a] * sp[a] / level_mm)));
  if (dims == intraop.grid.dims) return fine;
  return resample_linear(fine, same_extent_grid(intraop.grid, dims));
}

struct Score {
  double ncc = 0, inside = 0;
  double objective() const { return inside < 0.5 ? -1.0 : ncc * ncc; }
};

// The sums over the two halves of the samples, side by side (the search
// evaluates this hundreds of times), reduced in a fixed order: the same
// result on one core or two.
Score score(const IntensityPlacementPreop::Level& s, const ImageF& image, const Eigen::Matrix4d& t) {
  struct Sums {
    double sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
    std::size_t n = 0;
  };
  std::array<Sums, 2> half;
  // Preop world -> scan voxel in one affine map.
  const Eigen::Matrix4d m = image.grid.voxel_from_world() * t;
  const Eigen::Matrix3d a = m.topLeftCorner<3, 3>();
  const Eigen::Vector3d b = m.topRightCorner<3, 1>();
  on_two_halves(s.at_mm.size(), [&](std::size_t begin, std::size_t end, std::size_t h) {
    Sums& sum = half[h];
    for (std::size_t i = begin; i < end; ++i) {
      const Eigen::Vector3d v = a * s.at_mm[i].cast<double>() + b;
      double y;
      if (!trilinear_sample<TrilinearEdge::kVoxelExtent>(image.grid, image.voxels.data(), v, &y)) continue;
      const double x = s.value[i];
      sum.sx += x, sum.sy += y, sum.sxx += x * x, sum.syy += y * y, sum.sxy += x * y;
      ++sum.n;
    }
  });
  const double sx = half[0].sx + half[1].sx, sy = half[0].sy + half[1].sy, sxx = half[0].sxx + half[1].sxx;
  const double syy = half[0].syy + half[1].syy, sxy = half[0].sxy + half[1].sxy;
  const std::size_t n = half[0].n + half[1].n;
  Score out;
  out.inside = s.at_mm.empty() ? 0 : static_cast<double>(n) / static_cast<double>(s.at_mm.size());
  if (n < 2) return out;
  const double dn = static_cast<double>(n);
  const double vx = sxx - sx * sx / dn, vy = syy - sy * sy / dn;
  if (vx <= 0 || vy <= 0) return out;
  out.ncc = (sxy - sx * sy / dn) / std::sqrt(vx * vy);
  return out;
}

}  // namespace

IntensityPlacementPreop intensity_placement_preop(const ImageF& preop_t1, const Mask& preop_brain,
                                                  const IntensityPlacementParameters& p) {
  if (!preop_t1.grid.same_geometry(preop_brain.grid)) throw InputError("intensity placement: preop T1 and brain on different grids");
  const MaskMoments moments = mask_moments(preop_brain);
  if (moments.volume_ml <= 0) throw InputError("intensity placement: the preop brain is empty");
  IntensityPlacementPreop out;
  out.centre_mm = moments.centroid_mm;
  for (const double level_mm : {p.coarse_mm, p.fine_mm})
    out.levels.push_back(level_samples(smoothed(preop_t1, level_mm), preop_brain, level_mm, p.max_samples));
  return out;
}

IntensityPlacementScan intensity_placement_scan(const IntensityPlacementPreop& preop, const ImageF& intraop) {
  IntensityPlacementScan out;
  for (const IntensityPlacementPreop::Level& level : preop.levels)
    out.levels.push_back(scan_at_level(intraop, level.smoothing_mm));
  return out;
}

IntensityPlacement place_by_intensity(const ImageF& preop_t1, const Mask& preop_brain, const ImageF& intraop,
                                      const Eigen::Matrix4d& start, const IntensityPlacementParameters& p) {
  const IntensityPlacementPreop preop = intensity_placement_preop(preop_t1, preop_brain, p);
  return place_by_intensity(preop, intensity_placement_scan(preop, intraop), start, p);
}

namespace {

void check_levels(const IntensityPlacementPreop& preop, const IntensityPlacementScan& scan,
                  const IntensityPlacementParameters& p) {
  if (preop.levels.size() != 2 || preop.levels[0].smoothing_mm != p.coarse_mm || preop.levels[1].smoothing_mm != p.fine_mm)
    throw InputError("intensity placement: the preop's samples were made for other levels");
  if (scan.levels.size() != preop.levels.size())
    throw InputError("intensity placement: the scan's levels were made for another preop");
}

std::array<double, 7> first_steps(const IntensityPlacementParameters& p) {
  const double deg = kPi / 180.0;
  return {p.translation_step_mm,     p.translation_step_mm,     p.translation_step_mm, p.rotation_step_deg * deg,
          p.rotation_step_deg * deg, p.rotation_step_deg * deg, p.log_scale_step};
}

// Pattern search from q: each of the first `parameters` tried a step either
// way, the best move kept; the steps halve when none helps, down to
// step[0] at most min_step_mm. Bounded by max_evaluations. Returns q's score.
Score pattern_search(const IntensityPlacementPreop::Level& s, const ImageF& image, const Eigen::Vector3d& centre,
                     const Eigen::Matrix4d& start, int parameters, double max_log_scale, double min_step_mm,
                     int max_evaluations, std::array<double, 7> step, Params& q, int& evaluations) {
  Score best = score(s, image, transform_of(q, centre, start));
  ++evaluations;
  int used = 0;
  while (used < max_evaluations && step[0] >= min_step_mm - 1e-12) {
    Params best_q = q;
    Score best_move = best;
    for (int a = 0; a < parameters && used < max_evaluations; ++a)
      for (const double sign : {-1.0, 1.0}) {
        Params trial = q;
        trial[static_cast<std::size_t>(a)] += sign * step[static_cast<std::size_t>(a)];
        if (std::abs(trial[6]) > max_log_scale) continue;
        const Score sc = score(s, image, transform_of(trial, centre, start));
        ++used;
        if (sc.objective() > best_move.objective() + 1e-9) best_move = sc, best_q = trial;
      }
    if (best_q == q) {
      for (double& x : step) x *= 0.5;
    } else {
      q = best_q;
      best = best_move;
    }
  }
  evaluations += used;
  return best;
}

// Every k-th sample, at most max_samples of them.
IntensityPlacementPreop::Level thinned(const IntensityPlacementPreop::Level& s, std::size_t max_samples) {
  if (s.at_mm.size() <= max_samples) return s;
  IntensityPlacementPreop::Level out;
  out.smoothing_mm = s.smoothing_mm;
  const std::size_t k = (s.at_mm.size() + max_samples - 1) / max_samples;
  for (std::size_t i = 0; i < s.at_mm.size(); i += k) out.at_mm.push_back(s.at_mm[i]), out.value.push_back(s.value[i]);
  return out;
}

}  // namespace

double intensity_correlation(const IntensityPlacementPreop& preop, const IntensityPlacementScan& intraop,
                             const Eigen::Matrix4d& intraop_from_preop, const IntensityPlacementParameters& p) {
  check_levels(preop, intraop, p);
  return score(preop.levels.back(), intraop.levels.back(), intraop_from_preop).ncc;
}

PoseSearch search_pose_by_intensity(const IntensityPlacementPreop& preop, const IntensityPlacementScan& intraop,
                                    const Eigen::Matrix4d& start, const IntensityPlacementParameters& p) {
  check_levels(preop, intraop, p);
  const Stopwatch watch;
  const IntensityPlacementPreop::Level few = thinned(preop.levels.front(), p.pose_samples);
  const ImageF& image = intraop.levels.front();
  const double deg = kPi / 180.0;
  std::array<double, 7> step{};
  for (int a = 0; a < 3; ++a) step[static_cast<std::size_t>(a)] = 2 * p.translation_step_mm;
  // The candidates, each searched on its own: the two halves of them side
  // by side (each evaluation on one thread), the best taken in candidate
  // order: the same answer on one core or two.
  std::vector<Params> candidates;
  for (const SweptPose& pose : swept_poses(p.pose_yaw_step_deg, p.pose_tilt_deg)) {
    Params q{};
    q[3] = pose.pitch_deg * deg, q[4] = pose.roll_deg * deg, q[5] = pose.yaw_deg * deg;
    if (q[5] > kPi) q[5] -= 2 * kPi;
    candidates.push_back(q);
  }
  std::vector<Score> scores(candidates.size());
  std::vector<int> evaluations(candidates.size(), 0);
  parallel_halves(candidates.size(), 1, [&](std::size_t begin, std::size_t end) {
    const SerialOnThisThread serial;
    for (std::size_t c = begin; c < end; ++c)
      scores[c] = pattern_search(few, image, preop.centre_mm, start, 3, 0.0, p.translation_step_mm / 2,
                                 p.pose_evaluations, step, candidates[c], evaluations[c]);
  });
  PoseSearch out;
  double best_objective = -2;
  for (std::size_t c = 0; c < candidates.size(); ++c) {
    ++out.candidates;
    out.evaluations += evaluations[c];
    if (scores[c].objective() > best_objective) {
      best_objective = scores[c].objective();
      out.intraop_from_preop = transform_of(candidates[c], preop.centre_mm, start);
      out.correlation = scores[c].ncc;
    }
  }
  out.rotation_from_start_deg =
      rotation_between_deg(start.topLeftCorner<3, 3>(), out.intraop_from_preop.topLeftCorner<3, 3>());
  out.seconds = watch.seconds();
  return out;
}

IntensityPlacement place_by_intensity(const IntensityPlacementPreop& preop, const IntensityPlacementScan& intraop,
                                      const Eigen::Matrix4d& start, const IntensityPlacementParameters& p) {
  check_levels(preop, intraop, p);
  const Eigen::Vector3d centre = preop.centre_mm;
  IntensityPlacement out;
  Params q{};
  const std::array<double, 7> first_step = first_steps(p);
  Score best;
  for (std::size_t level = 0; level < preop.levels.size(); ++level) {
    const IntensityPlacementPreop::Level& s = preop.levels[level];
    std::array<double, 7> step = first_step;
    if (s.smoothing_mm == p.fine_mm)
      for (double& x : step) x *= 0.5;
    best = pattern_search(s, intraop.levels[level], centre, start, p.max_log_scale > 0 ? 7 : 6,
                          p.max_log_scale, first_step[0] / p.finest_step_fraction, p.max_evaluations, step, q,
                          out.evaluations);
  }
  out.intraop_from_preop = transform_of(q, centre, start);
  out.correlation = best.ncc;
  out.inside_fraction = best.inside;
  out.message = "normalised correlation " + std::to_string(best.ncc) + " over " +
                std::to_string(static_cast<int>(100 * best.inside)) + " % of the preop brain's samples in view, " +
                std::to_string(out.evaluations) + " evaluations";
  return out;
}

}  // namespace brainshift
