#include "quality/left_right_check.h"

#include <algorithm>
#include <optional>

#include "image/resample.h"

namespace brainshift {
namespace {

Eigen::Vector3d voxel_centre(const Grid3& g, std::size_t v) {
  const std::size_t nx = g.dims[0], ny = g.dims[1];
  return g.world_mm(static_cast<double>(v % nx), static_cast<double>((v / nx) % ny), static_cast<double>(v / (nx * ny)));
}

// Symmetric overlap (a Dice of nearest-neighbour lookups, counted from both
// sides) of structure `label` when the preop is carried by intraop_from_preop.
double overlap(const std::vector<Eigen::Vector3d>& preop_points, const std::vector<Eigen::Vector3d>& intraop_points,
               const LabelImage& preop, const LabelImage& intraop, std::uint16_t label,
               const Eigen::Matrix4d& intraop_from_preop) {
  const GridSampler in_preop(preop.grid), in_intraop(intraop.grid);
  const Eigen::Matrix4d preop_from_intraop = intraop_from_preop.inverse();
  std::size_t hits = 0;
  for (const auto& p : preop_points)
    hits += in_intraop.nearest(intraop.voxels, (intraop_from_preop * p.homogeneous()).head<3>(), 0) == label;
  for (const auto& x : intraop_points)
    hits += in_preop.nearest(preop.voxels, (preop_from_intraop * x.homogeneous()).head<3>(), 0) == label;
  return static_cast<double>(hits) / static_cast<double>(preop_points.size() + intraop_points.size());
}

// The voxel centres of each structure, in one pass over the image.
std::vector<std::vector<Eigen::Vector3d>> points_of(const LabelImage& labels,
                                                    const std::vector<std::pair<std::string, std::uint16_t>>& structures) {
  std::vector<std::vector<Eigen::Vector3d>> out(structures.size());
  for (std::size_t v = 0; v < labels.voxels.size(); ++v) {
    const std::uint16_t l = labels.voxels[v];
    if (l == 0) continue;
    for (std::size_t s = 0; s < structures.size(); ++s)
      if (structures[s].second == l) out[s].push_back(voxel_centre(labels.grid, v));
  }
  return out;
}

// r^2 of the intraop T1 with the preop T1 carried by each of the two maps,
// over about 40k voxels of the intraop brain.
std::pair<double, double> image_scores(const LeftRightInput& in, const Eigen::Matrix4d& direct,
                                       const Eigen::Matrix4d& mirrored) {
  const Mask& brain = *in.intraop_brain;
  std::size_t inside = 0;
  for (auto m : brain.voxels) inside += m != 0;
  const std::size_t stride = std::max<std::size_t>(1, inside / 40000);
  const GridSampler preop(in.preop_t1->grid);
  const Eigen::Matrix4d d_inv = direct.inverse(), m_inv = mirrored.inverse();
  std::vector<double> fixed_v, direct_v, mirror_v;
  std::size_t seen = 0;
  for (std::size_t v = 0; v < brain.voxels.size(); ++v) {
    if (!brain.voxels[v] || (seen++ % stride) != 0) continue;
    const Eigen::Vector4d x = voxel_centre(brain.grid, v).homogeneous();
    fixed_v.push_back(in.intraop_t1->voxels[v]);
    direct_v.push_back(preop.linear(in.preop_t1->voxels, (d_inv * x).head<3>(), 0.f));
    mirror_v.push_back(preop.linear(in.preop_t1->voxels, (m_inv * x).head<3>(), 0.f));
  }
  return {squared_correlation(fixed_v, direct_v), squared_correlation(fixed_v, mirror_v)};
}

}  // namespace

Eigen::Matrix4d preop_mirror(const LabelImage& labels) {
  double sum_x = 0;
  std::size_t n = 0;
  for (std::size_t v = 0; v < labels.voxels.size(); ++v)
    if (labels.voxels[v] != 0) sum_x += voxel_centre(labels.grid, v).x(), ++n;
  const double c = n ? sum_x / static_cast<double>(n) : 0.0;
  Eigen::Matrix4d M = Eigen::Matrix4d::Identity();
  M(0, 0) = -1;
  M(0, 3) = 2 * c;
  return M;
}

LeftRightPreop left_right_preop(const LabelImage& preop_labels,
                                const std::vector<std::pair<std::string, std::uint16_t>>& structures) {
  return {structures, preop_mirror(preop_labels), points_of(preop_labels, structures)};
}

GateResult left_right_gate(const LeftRightInput& in, const PlausibilityLimits& limits) {
  GateResult g;
  g.name = "left_right";
  std::optional<LeftRightPreop> own;
  if (!in.preop_side || in.preop_side->structures != in.structures) own = left_right_preop(in.preop_labels, in.structures);
  const LeftRightPreop& preop = own ? *own : *in.preop_side;
  const Eigen::Matrix4d& A = in.intraop_from_preop;
  const Eigen::Matrix4d AM = A * preop.mirror;
  int prefer_mirror = 0, prefer_direct = 0;
  const auto vote = [&](double direct, double mirrored, double margin) {
    if (mirrored > direct + margin) ++prefer_mirror;
    if (direct > mirrored + margin) ++prefer_direct;
  };
  // A structure needs a few hundred voxels on both sides to say anything.
  constexpr std::size_t kMinVoxels = 200;
  const auto& preop_points_of = preop.points_mm;
  const auto intraop_points_of = points_of(in.intraop_labels, in.structures);
  for (std::size_t s = 0; s < in.structures.size(); ++s) {
    const auto& [name, label] = in.structures[s];
    const auto& preop_points = preop_points_of[s];
    const auto& intraop_points = intraop_points_of[s];
    if (preop_points.size() < kMinVoxels || intraop_points.size() < kMinVoxels) continue;
    const double d = overlap(preop_points, intraop_points, in.preop_labels, in.intraop_labels, label, A);
    const double m = overlap(preop_points, intraop_points, in.preop_labels, in.intraop_labels, label, AM);
    vote(d, m, limits.left_right_overlap_margin);
    g.extra[name] = {{"overlap_as_given", d}, {"overlap_mirrored", m}};
  }
  if (in.preop_t1 && in.intraop_t1 && in.intraop_brain) {
    const auto [d, m] = image_scores(in, A, AM);
    vote(d, m, limits.left_right_r2_margin);
    g.extra["image"] = {{"r2_as_given", d}, {"r2_mirrored", m}};
  }
  g.value = prefer_mirror - prefer_direct;
  g.limit = "<= 0";
  g.passed = g.value <= 0;
  g.detail = g.passed ? (prefer_direct > 0 ? "the scan fits the preop as given better than its mirror image"
                                           : "undecided: no asymmetric structure or image tells the sides apart")
                      : "the scan fits the preop's mirror image better than the preop: left and right swapped "
                        "(check the orientation of the conversion)";
  return g;
}

}  // namespace brainshift
