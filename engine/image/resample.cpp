#include "image/resample.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <vector>

#include "core/parallel.h"
#include "image/gaussian_smooth.h"

namespace brainshift {
namespace {

// Calls fn(output index, source voxel coordinate) for every target voxel,
// stepping the affine incrementally along x. fn writes only its own output
// voxel: the slices in two halves side by side, the same result.
template <class Fn>
void for_each_target(const Grid3& src, const Grid3& target, const Eigen::Matrix4d& src_from_target, Fn&& fn) {
  const Eigen::Matrix4d m = src.voxel_from_world() * src_from_target * target.world_from_voxel;
  const Eigen::Vector3d step = m.block<3, 1>(0, 0);
  parallel_halves(static_cast<std::size_t>(target.dims[2]), 8, [&](std::size_t k0, std::size_t k1) {
    for (auto k = static_cast<int>(k0); k < static_cast<int>(k1); ++k)
      for (int j = 0; j < target.dims[1]; ++j) {
        const Eigen::Vector3d row = (m * Eigen::Vector4d(0, j, k, 1)).head<3>();
        std::size_t out = target.index(0, j, k);
        for (int i = 0; i < target.dims[0]; ++i, ++out) fn(out, Eigen::Vector3d(row + i * step));
      }
  });
}

}  // namespace

float sample_linear(const ImageF& image, const Eigen::Vector3d& world_mm, float outside_value) {
  return GridSampler(image.grid).linear(image.voxels, world_mm, outside_value);
}

std::uint16_t sample_nearest(const LabelImage& labels, const Eigen::Vector3d& world_mm, std::uint16_t outside_value) {
  return GridSampler(labels.grid).nearest(labels.voxels, world_mm, outside_value);
}

ImageF resample_linear(const ImageF& src, const Grid3& target, const Eigen::Matrix4d& src_from_target,
                       float outside_value) {
  ImageF out(target, outside_value);
  for_each_target(src.grid, target, src_from_target, [&](std::size_t o, const Eigen::Vector3d& p) {
    double value;
    if (trilinear_sample<TrilinearEdge::kVoxelExtent>(src.grid, src.voxels.data(), p, &value))
      out.voxels[o] = static_cast<float>(value);
  });
  return out;
}

LabelImage resample_nearest(const LabelImage& src, const Grid3& target, const Eigen::Matrix4d& src_from_target,
                            std::uint16_t outside_value) {
  LabelImage out(target, outside_value);
  for_each_target(src.grid, target, src_from_target, [&](std::size_t o, const Eigen::Vector3d& p) {
    std::size_t index;
    if (nearest_voxel(src.grid, p, &index)) out.voxels[o] = src.voxels[index];
  });
  return out;
}

Grid3 same_extent_grid(const Grid3& grid, const std::array<int, 3>& dims) {
  Grid3 out;
  out.dims = dims;
  Eigen::Matrix4d from_out = Eigen::Matrix4d::Identity();
  for (int a = 0; a < 3; ++a) {
    // r source voxels per output voxel; output voxel -0.5 and n_out - 0.5
    // land on source voxel -0.5 and n - 0.5: the same box.
    const double r = static_cast<double>(grid.dims[a]) / std::max(1, dims[a]);
    from_out(a, a) = r;
    from_out(a, 3) = (r - 1) / 2;
  }
  out.world_from_voxel = grid.world_from_voxel * from_out;
  return out;
}

ImageF downsample_linear(const ImageF& image, const Grid3& coarser) {
  // Each voxel integrates over its extent (a box as wide as its spacing); a
  // Gaussian matched in variance to the wider box (sd = width / sqrt(12))
  // takes the source's profile to the coarser one's before the samples are
  // taken, so that noise finer than the new spacing does not alias.
  const Eigen::Vector3d fine = image.grid.spacing_mm(), coarse = coarser.spacing_mm();
  Eigen::Vector3d sigma_voxels;
  for (int a = 0; a < 3; ++a)
    sigma_voxels[a] = std::sqrt(std::max(0.0, coarse[a] * coarse[a] - fine[a] * fine[a]) / 12.0) / fine[a];
  ImageF smoothed = image;
  gaussian_smooth_voxels(smoothed, sigma_voxels);
  return resample_linear(smoothed, coarser);
}

namespace {

// The source voxels a coarser voxel's box overlaps along one axis, with the
// overlap in source voxels: coarser voxel j spans source coordinates
// [j r - 0.5, (j + 1) r - 0.5], r = n_source / n_coarser.
struct Overlap {
  int index;
  double weight;
};
std::vector<std::vector<Overlap>> axis_overlaps(int n_source, int n_coarser) {
  const double r = static_cast<double>(n_source) / n_coarser;
  std::vector<std::vector<Overlap>> out(static_cast<std::size_t>(n_coarser));
  for (int j = 0; j < n_coarser; ++j) {
    const double lo = j * r - 0.5, hi = (j + 1) * r - 0.5;
    for (int i = std::max(0, static_cast<int>(std::floor(lo + 0.5))); i < n_source && i - 0.5 < hi; ++i) {
      const double w = std::min(hi, i + 0.5) - std::max(lo, i - 0.5);
      if (w > 1e-9) out[static_cast<std::size_t>(j)].push_back({i, w});
    }
  }
  return out;
}

}  // namespace

Grid3 working_grid(const Grid3& image_grid, double working_spacing_mm) {
  if (!(working_spacing_mm > 0)) return image_grid;
  const Eigen::Vector3d spacing = image_grid.spacing_mm();
  std::array<int, 3> dims = image_grid.dims;
  bool coarser = false;
  for (int a = 0; a < 3; ++a) {
    if (spacing[a] * kWorkingGridMinCoarsening >= working_spacing_mm) continue;
    const double extent_mm = spacing[a] * image_grid.dims[a];
    dims[a] = std::max(1, static_cast<int>(std::lround(extent_mm / working_spacing_mm)));
    coarser = coarser || dims[a] < image_grid.dims[a];
  }
  return coarser ? same_extent_grid(image_grid, dims) : image_grid;
}

LabelImage downsample_labels(const LabelImage& labels, const Grid3& coarser) {
  const Grid3 expected = same_extent_grid(labels.grid, coarser.dims);
  if (!expected.world_from_voxel.isApprox(coarser.world_from_voxel, 1e-9))
    throw std::invalid_argument("downsample_labels: the coarser grid does not span the labels' box");
  std::array<std::vector<std::vector<Overlap>>, 3> axis;
  for (int a = 0; a < 3; ++a) axis[a] = axis_overlaps(labels.grid.dims[a], coarser.dims[a]);
  LabelImage out(coarser, 0);
  const auto& g = labels.grid;
  parallel_halves(static_cast<std::size_t>(coarser.dims[2]), 4, [&](std::size_t k0, std::size_t k1) {
    std::vector<std::pair<std::uint16_t, double>> cover;  // label, overlap
    for (auto k = static_cast<int>(k0); k < static_cast<int>(k1); ++k)
      for (int j = 0; j < coarser.dims[1]; ++j)
        for (int i = 0; i < coarser.dims[0]; ++i) {
          cover.clear();
          for (const Overlap& z : axis[2][static_cast<std::size_t>(k)])
            for (const Overlap& y : axis[1][static_cast<std::size_t>(j)])
              for (const Overlap& x : axis[0][static_cast<std::size_t>(i)]) {
                const std::uint16_t l = labels.voxels[g.index(x.index, y.index, z.index)];
                const double w = x.weight * y.weight * z.weight;
                auto it = std::find_if(cover.begin(), cover.end(), [l](const auto& c) { return c.first == l; });
                if (it == cover.end()) cover.emplace_back(l, w);
                else it->second += w;
              }
          // Most cover; an exact tie (the same sums of the same overlaps)
          // to the lowest label on even voxels, the highest on odd ones.
          const bool odd = (i + j + k) % 2 != 0;
          std::pair<std::uint16_t, double> best{0, -1.0};
          for (const auto& c : cover)
            if (c.second > best.second || (c.second == best.second && (c.first < best.first) != odd)) best = c;
          out.voxels[coarser.index(i, j, k)] = best.first;
        }
  });
  return out;
}

}  // namespace brainshift
