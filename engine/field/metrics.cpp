#include "field/metrics.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "field/vector_sampling.h"
#include "image/distance_map.h"

namespace brainshift {
namespace {

void require_same_grid(const Grid3& a, const Grid3& b, const char* what) {
  if (!a.same_geometry(b)) {
    throw InputError(std::string(what) + ": the two images are not on the same grid");
  }
}

double voxel_ml(const Grid3& g) {
  return std::abs(g.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
}

// Distances from each boundary voxel of `from` to the nearest boundary voxel of `to`.
void directed_distances(const Mask& from_boundary, const ImageF& to_distance, std::vector<double>& out) {
  for (std::size_t v = 0; v < from_boundary.voxels.size(); ++v) {
    if (from_boundary.voxels[v]) out.push_back(to_distance.voxels[v]);
  }
}

}  // namespace

std::vector<LabelDice> dice_per_label(const LabelImage& a, const LabelImage& b,
                                      const std::vector<std::uint16_t>& labels) {
  require_same_grid(a.grid, b.grid, "dice_per_label");
  std::vector<LabelDice> result;
  for (const std::uint16_t label : labels) {
    std::size_t na = 0, nb = 0, both = 0;
    for (std::size_t v = 0; v < a.voxels.size(); ++v) {
      const bool in_a = a.voxels[v] == label, in_b = b.voxels[v] == label;
      na += in_a;
      nb += in_b;
      both += in_a && in_b;
    }
    LabelDice d;
    d.label = label;
    d.dice = na + nb == 0 ? 1.0 : 2.0 * static_cast<double>(both) / static_cast<double>(na + nb);
    d.volume_a_ml = na * voxel_ml(a.grid);
    d.volume_b_ml = nb * voxel_ml(b.grid);
    result.push_back(d);
  }
  return result;
}

SurfaceDistance surface_distance(const Mask& a, const Mask& b) {
  require_same_grid(a.grid, b.grid, "surface_distance");
  const Mask ba = boundary_voxels(a), bb = boundary_voxels(b);
  SurfaceDistance s;
  s.boundary_voxels_a = static_cast<std::size_t>(std::count(ba.voxels.begin(), ba.voxels.end(), 1));
  s.boundary_voxels_b = static_cast<std::size_t>(std::count(bb.voxels.begin(), bb.voxels.end(), 1));
  if (s.boundary_voxels_a == 0 || s.boundary_voxels_b == 0) {
    throw InputError("surface_distance: a mask has no boundary voxel");
  }
  std::vector<double> d;
  d.reserve(s.boundary_voxels_a + s.boundary_voxels_b);
  directed_distances(ba, distance_to_mask_mm(bb), d);
  directed_distances(bb, distance_to_mask_mm(ba), d);
  double sum = 0.0;
  for (const double x : d) sum += x;
  s.mean_mm = sum / d.size();
  s.hausdorff_mm = *std::max_element(d.begin(), d.end());
  s.hd95_mm = percentile(std::move(d), 95.0);
  return s;
}

namespace {

// det(I + grad u) at voxel (i,j,k): central differences in index space (one-
// sided at the border), mapped to world mm through the grid's affine.
float jacobian_at(const VectorImage3& field, const Eigen::Matrix3d& index_from_world,
                  const std::array<std::size_t, 3>& stride, int i, int j, int k) {
  const Grid3& g = field.grid;
  const std::array<int, 3> ijk{i, j, k};
  const std::size_t v = g.index(i, j, k);
  Eigen::Matrix3d d_index;  // column a = du / d index_a
  for (int a = 0; a < 3; ++a) {
    const bool has_lo = ijk[a] > 0, has_hi = ijk[a] + 1 < g.dims[a];
    if (!has_lo && !has_hi) {
      d_index.col(a).setZero();
      continue;
    }
    const std::size_t hi = has_hi ? v + stride[a] : v;
    const std::size_t lo = has_lo ? v - stride[a] : v;
    const double h = (has_hi && has_lo) ? 2.0 : 1.0;
    d_index.col(a) = (field.vectors[hi] - field.vectors[lo]).cast<double>() / h;
  }
  const Eigen::Matrix3d jac = Eigen::Matrix3d::Identity() + d_index * index_from_world;
  return static_cast<float>(jac.determinant());
}

// Visits every voxel (or only those in mask) of slices [k_begin, k_end) with
// its determinant.
template <class Visit>
void for_each_jacobian(const VectorImage3& field, const Mask* mask, int k_begin, int k_end, Visit&& visit) {
  const Grid3& g = field.grid;
  // d(world)/d(index) = M, so grad_world u = (du/d index) * M^-1.
  const Eigen::Matrix3d index_from_world = g.world_from_voxel.topLeftCorner<3, 3>().inverse();
  const std::array<std::size_t, 3> stride{1, static_cast<std::size_t>(g.dims[0]),
                                          static_cast<std::size_t>(g.dims[0]) * g.dims[1]};
  for (int k = k_begin; k < k_end; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        if (mask && !mask->voxels[v]) continue;
        visit(v, jacobian_at(field, index_from_world, stride, i, j, k));
      }
}

}  // namespace

double jacobian_determinant_at(const VectorImage3& field, int i, int j, int k) {
  const Grid3& g = field.grid;
  const Eigen::Matrix3d index_from_world = g.world_from_voxel.topLeftCorner<3, 3>().inverse();
  const std::array<std::size_t, 3> stride{1, static_cast<std::size_t>(g.dims[0]),
                                          static_cast<std::size_t>(g.dims[0]) * g.dims[1]};
  return jacobian_at(field, index_from_world, stride, i, j, k);
}

ImageF jacobian_determinant(const VectorImage3& field) {
  ImageF det(field.grid, 0.f);
  for_each_jacobian(field, nullptr, 0, field.grid.dims[2], [&det](std::size_t v, float d) { det.voxels[v] = d; });
  return det;
}

JacobianStats jacobian_stats(const VectorImage3& field, const Mask* mask) {
  if (mask) require_same_grid(field.grid, mask->grid, "jacobian_stats");
  // Only the masked voxels are evaluated: the brain is a fraction of the
  // grid. The two halves' slices side by side; minima, maxima and counts
  // merge exactly.
  std::array<JacobianStats, 2> half;
  for (auto& h : half) {
    h.min_det = std::numeric_limits<double>::infinity();
    h.max_det = -std::numeric_limits<double>::infinity();
  }
  const int nz = field.grid.dims[2];
  on_two_halves(static_cast<std::size_t>(nz), [&](std::size_t k0, std::size_t k1, std::size_t h) {
    // Kept here and stored once: the two halves' stats share a cache line.
    JacobianStats s = half[h];
    for_each_jacobian(field, mask, static_cast<int>(k0), static_cast<int>(k1), [&s](std::size_t, float det) {
      const double d = det;
      s.min_det = std::min(s.min_det, d);
      s.max_det = std::max(s.max_det, d);
      s.folded_voxels += d <= 0.0;
      ++s.voxels;
    });
    half[h] = s;
  });
  JacobianStats s = half[0];
  s.min_det = std::min(half[0].min_det, half[1].min_det);
  s.max_det = std::max(half[0].max_det, half[1].max_det);
  s.folded_voxels += half[1].folded_voxels;
  s.voxels += half[1].voxels;
  if (s.voxels == 0) s.min_det = s.max_det = 0.0;
  return s;
}

double percentile(std::vector<double> values, double q) {
  if (values.empty()) throw InputError("percentile of an empty list");
  std::sort(values.begin(), values.end());
  const double pos = std::clamp(q, 0.0, 100.0) / 100.0 * (values.size() - 1);
  const std::size_t lo = static_cast<std::size_t>(std::floor(pos));
  const std::size_t hi = std::min(lo + 1, values.size() - 1);
  return values[lo] + (pos - lo) * (values[hi] - values[lo]);
}

TreStats target_registration_error(const VectorImage3& pullback,
                                   const std::vector<Eigen::Vector3d>& intraop_points_mm,
                                   const std::vector<Eigen::Vector3d>& preop_points_mm) {
  if (intraop_points_mm.size() != preop_points_mm.size() || intraop_points_mm.empty()) {
    throw InputError("target_registration_error: need the same, non-zero number of intraop (" +
                     std::to_string(intraop_points_mm.size()) + ") and preop (" +
                     std::to_string(preop_points_mm.size()) + ") points");
  }
  TreStats s;
  for (std::size_t n = 0; n < intraop_points_mm.size(); ++n) {
    const auto u = sample_vector_linear(pullback, intraop_points_mm[n]);
    if (!u) {
      throw InputError("target_registration_error: landmark " + std::to_string(n) +
                       " lies outside the displacement field");
    }
    s.errors_mm.push_back((intraop_points_mm[n] + *u - preop_points_mm[n]).norm());
  }
  double sum = 0.0;
  for (const double e : s.errors_mm) sum += e;
  s.mean_mm = sum / s.errors_mm.size();
  s.median_mm = percentile(s.errors_mm, 50.0);
  s.p95_mm = percentile(s.errors_mm, 95.0);
  s.max_mm = *std::max_element(s.errors_mm.begin(), s.errors_mm.end());
  return s;
}

void to_json(nlohmann::json& j, const LabelDice& d) {
  j = {{"label", d.label}, {"dice", d.dice}, {"volume_a_ml", d.volume_a_ml}, {"volume_b_ml", d.volume_b_ml}};
}
void to_json(nlohmann::json& j, const SurfaceDistance& s) {
  j = {{"mean_mm", s.mean_mm},
       {"hd95_mm", s.hd95_mm},
       {"hausdorff_mm", s.hausdorff_mm},
       {"boundary_voxels_a", s.boundary_voxels_a},
       {"boundary_voxels_b", s.boundary_voxels_b}};
}
void to_json(nlohmann::json& j, const JacobianStats& s) {
  j = {{"min_det", s.min_det}, {"max_det", s.max_det}, {"folded_voxels", s.folded_voxels}, {"voxels", s.voxels}};
}
void to_json(nlohmann::json& j, const TreStats& s) {
  j = {{"mean_mm", s.mean_mm},     {"median_mm", s.median_mm}, {"p95_mm", s.p95_mm},
       {"max_mm", s.max_mm},       {"count", s.errors_mm.size()}, {"errors_mm", s.errors_mm}};
}

}  // namespace brainshift
