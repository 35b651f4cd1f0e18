#include "image/morphology.h"

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "image/distance_map.h"
#include "image/image_stats.h"

namespace brainshift {
namespace {

struct Offset {
  int di, dj, dk;
};

std::vector<Offset> neighbourhood(int connectivity) {
  if (connectivity != 6 && connectivity != 26)
    throw InputError("connectivity must be 6 or 26, got " + std::to_string(connectivity));
  std::vector<Offset> offs;
  for (int dk = -1; dk <= 1; ++dk)
    for (int dj = -1; dj <= 1; ++dj)
      for (int di = -1; di <= 1; ++di) {
        const int manhattan = std::abs(di) + std::abs(dj) + std::abs(dk);
        if (manhattan == 0 || (connectivity == 6 && manhattan != 1)) continue;
        offs.push_back({di, dj, dk});
      }
  return offs;
}

// Flood fill from `seed` over voxels where accept(index) holds and label is 0.
template <class Accept>
void flood(const Grid3& g, std::size_t seed, std::int32_t id, const std::vector<Offset>& offs,
           std::vector<std::int32_t>& label, Accept&& accept, std::vector<std::size_t>& stack) {
  const std::size_t nx = g.dims[0], nxy = nx * g.dims[1];
  label[seed] = id;
  stack.assign(1, seed);
  while (!stack.empty()) {
    const std::size_t v = stack.back();
    stack.pop_back();
    const int i = static_cast<int>(v % nx), j = static_cast<int>((v / nx) % g.dims[1]),
              k = static_cast<int>(v / nxy);
    for (const Offset& o : offs) {
      if (!g.contains(i + o.di, j + o.dj, k + o.dk)) continue;
      const std::size_t n = g.index(i + o.di, j + o.dj, k + o.dk);
      if (label[n] == 0 && accept(n)) {
        label[n] = id;
        stack.push_back(n);
      }
    }
  }
}

// Slack so that a voxel exactly at radius_mm is inside despite float rounding.
double radius_squared(double radius_mm) {
  if (!(radius_mm >= 0.0)) throw InputError("morphology radius must be >= 0 mm, got " + std::to_string(radius_mm));
  return radius_mm * radius_mm * (1.0 + 1e-6) + 1e-9;
}

}  // namespace

Mask mask_of_labels(const LabelImage& labels, const std::vector<std::uint16_t>& values) {
  std::vector<std::uint8_t> wanted(65536, 0);
  for (std::uint16_t v : values) wanted[v] = 1;
  Mask out(labels.grid, 0);
  for (std::size_t i = 0; i < out.voxels.size(); ++i) out.voxels[i] = wanted[labels.voxels[i]];
  return out;
}

Mask mask_of_labels(const LabelImage& labels, std::initializer_list<std::uint16_t> values) {
  return mask_of_labels(labels, std::vector<std::uint16_t>(values));
}

Mask threshold(const ImageF& image, float lower, float upper) {
  Mask out(image.grid, 0);
  for (std::size_t i = 0; i < out.voxels.size(); ++i)
    out.voxels[i] = image.voxels[i] >= lower && image.voxels[i] <= upper;
  return out;
}

Image3<std::int32_t> connected_components(const Mask& mask, int connectivity, int* count) {
  const auto offs = neighbourhood(connectivity);
  Image3<std::int32_t> comp(mask.grid, 0);
  std::vector<std::size_t> stack;
  std::int32_t n = 0;
  const std::uint8_t* m = mask.voxels.data();
  for (std::size_t v = 0; v < mask.voxels.size(); ++v)
    if (m[v] && comp.voxels[v] == 0)
      flood(mask.grid, v, ++n, offs, comp.voxels, [m](std::size_t i) { return m[i] != 0; }, stack);
  if (count) *count = n;
  return comp;
}

Mask largest_component(const Mask& mask, int connectivity) {
  int n = 0;
  const auto comp = connected_components(mask, connectivity, &n);
  Mask out(mask.grid, 0);
  if (n == 0) return out;
  std::vector<std::size_t> sizes(n + 1, 0);
  for (std::int32_t c : comp.voxels) ++sizes[c];
  sizes[0] = 0;
  const auto best = static_cast<std::int32_t>(std::max_element(sizes.begin(), sizes.end()) - sizes.begin());
  for (std::size_t i = 0; i < out.voxels.size(); ++i) out.voxels[i] = comp.voxels[i] == best;
  return out;
}

// The background reached from outside the grid, 6-connected. The grid is
// padded by two layers: the outer one is a wall, the inner one a background
// shell that touches every border voxel, so one flood from a shell voxel
// reaches what a flood from every background border voxel would, and no
// neighbour needs a bounds check (this runs on every outline mask of a scan).
Mask fill_holes(const Mask& mask) {
  // Only the mask's bounding box needs the flood: every voxel outside it
  // reaches the border along an axis, and a path from inside the box to the
  // border leaves the box through the ring around it. A brain fills a third
  // of a scan's grid, so this is a fraction of the work.
  const Grid3& g = mask.grid;
  Mask out = mask;
  const VoxelBox box = bounding_box_voxels(mask);
  if (box.empty) return out;
  const std::ptrdiff_t nx = box.hi[0] - box.lo[0] + 1, ny = box.hi[1] - box.lo[1] + 1, nz = box.hi[2] - box.lo[2] + 1;
  const std::ptrdiff_t px = nx + 4, py = ny + 4, pz = nz + 4, pxy = px * py;
  enum : std::uint8_t { kOpen = 0, kWall = 1, kReached = 2 };
  std::vector<std::uint8_t> state(static_cast<std::size_t>(pxy * pz), kOpen);
  for (std::ptrdiff_t k = 0; k < pz; ++k)
    for (std::ptrdiff_t j = 0; j < py; ++j)
      for (std::ptrdiff_t i = 0; i < px; ++i)
        if (i == 0 || j == 0 || k == 0 || i == px - 1 || j == py - 1 || k == pz - 1)
          state[static_cast<std::size_t>(k * pxy + j * px + i)] = kWall;
  const std::uint8_t* m = mask.voxels.data();
  auto padded = [&](std::ptrdiff_t i, std::ptrdiff_t j, std::ptrdiff_t k) {
    return static_cast<std::size_t>((k + 2) * pxy + (j + 2) * px + (i + 2));
  };
  auto full = [&](std::ptrdiff_t i, std::ptrdiff_t j, std::ptrdiff_t k) {
    return g.index(static_cast<int>(i) + box.lo[0], static_cast<int>(j) + box.lo[1], static_cast<int>(k) + box.lo[2]);
  };
  for (std::ptrdiff_t k = 0; k < nz; ++k)
    for (std::ptrdiff_t j = 0; j < ny; ++j)
      for (std::ptrdiff_t i = 0; i < nx; ++i)
        if (m[full(i, j, k)]) state[padded(i, j, k)] = kWall;
  const std::ptrdiff_t step[6] = {1, -1, px, -px, pxy, -pxy};
  std::vector<std::size_t> stack{static_cast<std::size_t>(pxy + px + 1)};
  state[stack.back()] = kReached;
  while (!stack.empty()) {
    const std::size_t at = stack.back();
    stack.pop_back();
    for (std::ptrdiff_t s : step) {
      const std::size_t n = static_cast<std::size_t>(static_cast<std::ptrdiff_t>(at) + s);
      if (state[n] == kOpen) {
        state[n] = kReached;
        stack.push_back(n);
      }
    }
  }
  for (std::ptrdiff_t k = 0; k < nz; ++k)
    for (std::ptrdiff_t j = 0; j < ny; ++j)
      for (std::ptrdiff_t i = 0; i < nx; ++i)
        if (state[padded(i, j, k)] == kOpen) out.voxels[full(i, j, k)] = 1;
  return out;
}

Mask boundary_voxels(const Mask& mask) {
  Mask out(mask.grid, 0);
  const auto& n = mask.grid.dims;
  // Each slice on its own: the two halves side by side.
  parallel_halves(static_cast<std::size_t>(n[2]), 4, [&](std::size_t k0, std::size_t k1) {
    for (int k = static_cast<int>(k0); k < static_cast<int>(k1); ++k)
      for (int j = 0; j < n[1]; ++j)
        for (int i = 0; i < n[0]; ++i) {
          if (!mask.at(i, j, k)) continue;
          const bool edge = (i > 0 && !mask.at(i - 1, j, k)) || (i + 1 < n[0] && !mask.at(i + 1, j, k)) ||
                            (j > 0 && !mask.at(i, j - 1, k)) || (j + 1 < n[1] && !mask.at(i, j + 1, k)) ||
                            (k > 0 && !mask.at(i, j, k - 1)) || (k + 1 < n[2] && !mask.at(i, j, k + 1));
          out.at(i, j, k) = edge;
        }
  });
  return out;
}

namespace {

// op (a dilation or erosion by radius_mm) on the mask's bounding box grown by
// the radius and a voxel, clipped to the grid, pasted back: the same mask as
// op on the whole grid, for a fraction of its distance map when the mask is
// small in its grid (the ventricles, fluid inside the brain). Exact: a dilation
// is 0 farther than the radius from every mask voxel; an erosion is 0 outside
// the mask, and inside it a background voxel within the radius lies in the
// grown box (the grid's own edge is no background, in the box as in the grid).
template <class Op>
Mask within_reach(const Mask& mask, double radius_mm, Op op) {
  const VoxelBox tight = bounding_box_voxels(mask);
  if (tight.empty) return Mask(mask.grid, 0);
  const VoxelBox box = grow_box(tight, mask.grid, radius_mm + mask.grid.spacing_mm().maxCoeff());
  const auto& n = mask.grid.dims;
  if (box.lo == std::array<int, 3>{0, 0, 0} && box.hi == std::array<int, 3>{n[0] - 1, n[1] - 1, n[2] - 1})
    return op(mask);
  const Mask part = op(crop_to_box(mask, box));
  Mask out(mask.grid, 0);
  for (int k = 0; k < part.grid.dims[2]; ++k)
    for (int j = 0; j < part.grid.dims[1]; ++j) {
      const std::uint8_t* src = &part.voxels[part.grid.index(0, j, k)];
      std::copy(src, src + part.grid.dims[0], &out.voxels[mask.grid.index(box.lo[0], j + box.lo[1], k + box.lo[2])]);
    }
  return out;
}

// The nearest feature to any voxel that is not one is a boundary voxel:
// from a feature whose neighbours are all features, one step toward the
// point is a feature and nearer. So distances from boundary_voxels equal
// distances from the whole mask everywhere but on the mask, and lines
// through the inside of a large mask are left infinite by the capped map
// (no work).
// Dilation: the mask, and every voxel within the radius of its boundary; the
// distance map is needed only up to the radius (squared_distance_to_mask_mm2's cap).
Mask dilate_whole(const Mask& mask, double r2) {
  const ImageF d2 = squared_distance_to_mask_mm2(boundary_voxels(mask), r2);
  Mask out(mask.grid, 0);
  for (std::size_t i = 0; i < out.voxels.size(); ++i) out.voxels[i] = mask.voxels[i] || d2.voxels[i] <= r2;
  return out;
}

// Erosion: the mask less every voxel within the radius of the background.
Mask erode_whole(const Mask& mask, double r2) {
  Mask background(mask.grid, 0);
  for (std::size_t i = 0; i < mask.voxels.size(); ++i) background.voxels[i] = mask.voxels[i] == 0;
  const ImageF d2 = squared_distance_to_mask_mm2(boundary_voxels(background), r2);
  Mask out(mask.grid, 0);
  for (std::size_t i = 0; i < out.voxels.size(); ++i) out.voxels[i] = mask.voxels[i] && d2.voxels[i] > r2;
  return out;
}

}  // namespace

Mask dilate(const Mask& mask, double radius_mm) {
  const double r2 = radius_squared(radius_mm);
  return within_reach(mask, radius_mm, [&](const Mask& m) { return dilate_whole(m, r2); });
}

Mask erode(const Mask& mask, double radius_mm) {
  const double r2 = radius_squared(radius_mm);
  return within_reach(mask, radius_mm, [&](const Mask& m) { return erode_whole(m, r2); });
}

Mask close(const Mask& mask, double radius_mm) { return erode(dilate(mask, radius_mm), radius_mm); }
Mask open(const Mask& mask, double radius_mm) { return dilate(erode(mask, radius_mm), radius_mm); }

}  // namespace brainshift
