#pragma once
// Registration quality measures on the intraop grid, and their JSON form.
// All distances are world mm; all masks/labels must share one grid (InputError
// otherwise).
#include <Eigen/Dense>
#include <cstddef>
#include <cstdint>
#include <nlohmann/json_fwd.hpp>
#include <vector>

#include "core/image.h"
#include "image/morphology.h"

namespace brainshift {

// ---- overlap
struct LabelDice {
  std::uint16_t label = 0;
  double dice = 0.0;        // 2|A n B| / (|A| + |B|); 1 when both are empty
  double volume_a_ml = 0.0;
  double volume_b_ml = 0.0;
};
// One entry per requested label (e.g. warped preop labels vs intraop labels).
std::vector<LabelDice> dice_per_label(const LabelImage& a, const LabelImage& b,
                                      const std::vector<std::uint16_t>& labels);

// ---- surface distances
// Boundary voxels: mask voxels with a 6-neighbour in the background (neighbours
// outside the grid do not count, as in image/morphology.h). Each boundary voxel
// of A is measured to the nearest boundary voxel centre of B with an exact
// distance map, and vice versa. mean_mm is the mean over both sets together
// (mean symmetric surface distance); hd95_mm the 95th percentile of both sets
// together (as MedPy's hd95); hausdorff_mm the maximum.
struct SurfaceDistance {
  double mean_mm = 0.0;
  double hd95_mm = 0.0;
  double hausdorff_mm = 0.0;
  std::size_t boundary_voxels_a = 0;
  std::size_t boundary_voxels_b = 0;
};
// InputError when either mask has no boundary voxel (distance undefined).
SurfaceDistance surface_distance(const Mask& a, const Mask& b);

// ---- Jacobian of x -> x + u(x)
// det(I + grad u) with grad u from central differences in voxel index space
// (one-sided on the grid faces) mapped to world mm through the grid's linear part.
ImageF jacobian_determinant(const VectorImage3& field);
// The same at one voxel (central differences, one-sided at the border).
double jacobian_determinant_at(const VectorImage3& field, int i, int j, int k);
struct JacobianStats {
  double min_det = 0.0;
  double max_det = 0.0;
  std::size_t folded_voxels = 0;  // det <= 0
  std::size_t voxels = 0;         // voxels evaluated (inside the mask)
};
// mask may be null (whole grid); otherwise it must share the field's grid.
JacobianStats jacobian_stats(const VectorImage3& field, const Mask* mask);

// ---- target registration error
// TRE_i = |x_i + u(x_i) - p_i| with u sampled trilinearly; x_i intraop points,
// p_i their true preop points (world mm). InputError if the lists differ in
// length, are empty, or a point lies outside the field.
// Percentiles interpolate linearly between order statistics (numpy's default).
struct TreStats {
  std::vector<double> errors_mm;
  double mean_mm = 0.0;
  double median_mm = 0.0;
  double p95_mm = 0.0;
  double max_mm = 0.0;
};
TreStats target_registration_error(const VectorImage3& pullback,
                                   const std::vector<Eigen::Vector3d>& intraop_points_mm,
                                   const std::vector<Eigen::Vector3d>& preop_points_mm);

// q-th percentile (0..100) with linear interpolation; values need not be sorted.
double percentile(std::vector<double> values, double q);

// ---- JSON (nlohmann ADL hooks: json j = stats;)
void to_json(nlohmann::json& j, const LabelDice& d);
void to_json(nlohmann::json& j, const SurfaceDistance& s);
void to_json(nlohmann::json& j, const JacobianStats& s);
void to_json(nlohmann::json& j, const TreStats& s);  // includes the per-point errors

}  // namespace brainshift
