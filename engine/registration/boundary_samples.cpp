#include "registration/boundary_samples.h"

#include "image/image_stats.h"

#include <algorithm>
#include <random>
#include <string>

#include "core/errors.h"
#include "image/distance_map.h"

namespace brainshift {

// Margin (mm) of the ventricles' cropped distance map around their bounding box.
constexpr double kVentricleMapMarginMm = 30.0;
namespace {

bool has_label(const LabelImage& labels, std::uint16_t value) {
  return std::find(labels.voxels.begin(), labels.voxels.end(), value) != labels.voxels.end();
}

void require_label(const LabelImage& labels, std::uint16_t value, const char* which) {
  if (labels.grid.voxel_count() == 0) {
    throw InputError(std::string(which) + " label map: the image is empty");
  }
  if (!has_label(labels, value)) {
    throw InputError(std::string(which) + " label map: no voxel has the brain label " +
                     std::to_string(value));
  }
}

// Fisher-Yates with our own index draw: std::shuffle's use of the engine is
// implementation-defined, and results must not depend on the standard library.
template <class T>
void deterministic_shuffle(std::vector<T>& items) {
  std::mt19937_64 rng(0x5eed5eedULL);
  for (std::size_t i = items.size(); i > 1; --i) {
    const std::size_t j = static_cast<std::size_t>(rng() % i);
    std::swap(items[i - 1], items[j]);
  }
}

}  // namespace

MaskMoments mask_moments(const Mask& mask) {
  const auto& g = mask.grid;
  Eigen::Vector3d sum_voxel = Eigen::Vector3d::Zero();
  Eigen::Matrix3d sum_outer = Eigen::Matrix3d::Zero();
  std::size_t count = 0;
  // Accumulate in voxel indices (exact, cheap), convert to world once: the map is affine.
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j) {
      const std::uint8_t* row = &mask.voxels[g.index(0, j, k)];
      for (int i = 0; i < g.dims[0]; ++i) {
        if (!row[i]) continue;
        const Eigen::Vector3d v(i, j, k);
        sum_voxel += v;
        sum_outer += v * v.transpose();
        ++count;
      }
    }
  MaskMoments m;
  if (count == 0) return m;
  const Eigen::Matrix3d linear = g.world_from_voxel.topLeftCorner<3, 3>();
  const Eigen::Vector3d mean_voxel = sum_voxel / double(count);
  const Eigen::Matrix3d cov_voxel = sum_outer / double(count) - mean_voxel * mean_voxel.transpose();
  m.volume_ml = double(count) * std::abs(linear.determinant()) / 1000.0;
  m.centroid_mm = g.world_mm(mean_voxel.x(), mean_voxel.y(), mean_voxel.z());
  m.covariance_mm2 = linear * cov_voxel * linear.transpose();
  return m;
}

std::vector<Eigen::Vector3d> mask_boundary_points_mm(const Mask& mask) {
  const auto& g = mask.grid;
  std::vector<Eigen::Vector3d> points;
  const std::array<std::size_t, 3> stride{1, static_cast<std::size_t>(g.dims[0]),
                                          static_cast<std::size_t>(g.dims[0]) * g.dims[1]};
  // Each face is visited once, from its lower-index voxel, so no duplicates.
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        const int ijk[3] = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          if (ijk[a] + 1 >= g.dims[a]) continue;
          if (mask.voxels[v] == mask.voxels[v + stride[a]]) continue;
          double c[3] = {double(i), double(j), double(k)};
          c[a] += 0.5;
          points.push_back(g.world_mm(c[0], c[1], c[2]));
        }
      }
  deterministic_shuffle(points);
  return points;
}

Mask outline_mask(const LabelImage& labels) { return fill_holes(nonzero_mask(labels)); }

PreopBoundarySamples prepare_preop_samples(const LabelImage& preop_labels,
                                           std::uint16_t brain_label,
                                           std::uint16_t ventricle_label) {
  require_label(preop_labels, brain_label, "preop");
  PreopBoundarySamples samples;
  const Mask outline = outline_mask(preop_labels);
  samples.outer_mm = mask_boundary_points_mm(outline);
  samples.outer_moments = mask_moments(outline);
  if (has_label(preop_labels, ventricle_label)) {
    samples.ventricle_mm = mask_boundary_points_mm(mask_of_labels(preop_labels, {ventricle_label}));
  }
  return samples;
}

IntraopDistanceMaps prepare_intraop_maps(const LabelImage& intraop_labels,
                                         std::uint16_t brain_label,
                                         std::uint16_t ventricle_label) {
  return prepare_intraop_maps(intraop_labels, outline_mask(intraop_labels), brain_label, ventricle_label);
}

IntraopDistanceMaps prepare_intraop_maps(const LabelImage& intraop_labels, const Mask& outline,
                                         std::uint16_t brain_label,
                                         std::uint16_t ventricle_label) {
  require_label(intraop_labels, brain_label, "intraop");
  IntraopDistanceMaps maps;
  maps.outer_sdf_mm = signed_distance_mm(outline);
  maps.outer_moments = mask_moments(outline);
  if (has_label(intraop_labels, ventricle_label)) {
    // The ventricles fill a small box: their distance map is computed only
    // within a margin around it (wider than any ventricle displacement the
    // affine leaves), on a grid placed at the same world position.
    const Mask ventricles = mask_of_labels(intraop_labels, {ventricle_label});
    const VoxelBox box = grow_box(bounding_box_voxels(ventricles), ventricles.grid, kVentricleMapMarginMm);
    maps.ventricle_sdf_mm = signed_distance_mm(crop_to_box(ventricles, box));
  }
  return maps;
}

}  // namespace brainshift
