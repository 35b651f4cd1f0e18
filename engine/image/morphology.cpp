#include "image/morphology.h"

#include <algorithm>
#include <array>
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

// The 6-connected components of the voxels (i, j, k) of a box of dims where
// in(i, j, k) holds, by runs: each row's runs of such voxels are joined to the
// runs they overlap in the row before (j - 1) and the slice before (k - 1)
// (the only 6-neighbours of a row before it), by union-find over the runs.
// A run visits its voxels once and a row's neighbours by run, not by voxel:
// several times faster than a voxel flood on the masks of a scan.
class RunComponents {
 public:
  struct Run {
    int i0, i1;        // inclusive, box coordinates
    std::size_t row;   // j + ny * k, box coordinates
  };

  template <class In>
  RunComponents(const std::array<int, 3>& dims, In&& in) {
    const int nx = dims[0], ny = dims[1], nz = dims[2];
    ny_ = static_cast<std::size_t>(ny);
    row_start_.assign(static_cast<std::size_t>(ny) * nz + 1, 0);
    for (int k = 0; k < nz; ++k)
      for (int j = 0; j < ny; ++j) {
        const std::size_t row = static_cast<std::size_t>(j) + static_cast<std::size_t>(ny) * k;
        row_start_[row] = runs_.size();
        for (int i = 0; i < nx;) {
          if (!in(i, j, k)) {
            ++i;
            continue;
          }
          const int i0 = i;
          while (i < nx && in(i, j, k)) ++i;
          runs_.push_back({i0, i - 1, row});
        }
      }
    row_start_.back() = runs_.size();
    parent_.resize(runs_.size());
    for (std::size_t r = 0; r < parent_.size(); ++r) parent_[r] = r;
    for (int k = 0; k < nz; ++k)
      for (int j = 0; j < ny; ++j) {
        const std::size_t row = static_cast<std::size_t>(j) + static_cast<std::size_t>(ny) * k;
        if (j > 0) join_rows(row - 1, row);
        if (k > 0) join_rows(row - static_cast<std::size_t>(ny), row);
      }
  }

  const std::vector<Run>& runs() const { return runs_; }
  // (j, k) of a run's row.
  std::array<int, 2> row_jk(const Run& run) const {
    return {static_cast<int>(run.row % ny_), static_cast<int>(run.row / ny_)};
  }

  std::size_t root(std::size_t r) {
    while (parent_[r] != r) r = parent_[r] = parent_[parent_[r]];
    return r;
  }

  // Component numbers 1..count in the raster order of each component's first
  // voxel (runs are made in raster order): as a flood from each first voxel
  // numbers them.
  std::vector<std::int32_t> numbers(std::int32_t* count) {
    std::vector<std::int32_t> of_root(runs_.size(), 0), out(runs_.size());
    std::int32_t n = 0;
    for (std::size_t r = 0; r < runs_.size(); ++r) {
      std::int32_t& id = of_root[root(r)];
      if (id == 0) id = ++n;
      out[r] = id;
    }
    if (count) *count = n;
    return out;
  }

 private:
  void join_rows(std::size_t a_row, std::size_t b_row) {
    std::size_t a = row_start_[a_row], b = row_start_[b_row];
    const std::size_t a_end = row_start_[a_row + 1], b_end = row_start_[b_row + 1];
    while (a < a_end && b < b_end) {
      if (runs_[a].i0 <= runs_[b].i1 && runs_[b].i0 <= runs_[a].i1) unite(a, b);
      if (runs_[a].i1 < runs_[b].i1) ++a;
      else ++b;
    }
  }
  void unite(std::size_t a, std::size_t b) {
    a = root(a), b = root(b);
    if (a != b) parent_[std::max(a, b)] = std::min(a, b);
  }

  std::size_t ny_ = 1;
  std::vector<Run> runs_;
  std::vector<std::size_t> row_start_;
  std::vector<std::size_t> parent_;
};

// Slack so that a voxel exactly at radius_mm is inside despite float rounding.
double radius_squared(double radius_mm) {
  if (!(radius_mm >= 0.0)) throw InputError("morphology radius must be >= 0 mm, got " + std::to_string(radius_mm));
  return radius_mm * radius_mm * (1.0 + 1e-6) + 1e-9;
}

}  // namespace

Mask nonzero_mask(const LabelImage& labels) {
  Mask mask(labels.grid, 0);
  for (std::size_t v = 0; v < labels.voxels.size(); ++v) mask.voxels[v] = labels.voxels[v] != 0;
  return mask;
}

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
  if (connectivity == 6) {
    const Grid3& g = mask.grid;
    const std::uint8_t* m = mask.voxels.data();
    RunComponents runs(g.dims, [&](int i, int j, int k) { return m[g.index(i, j, k)] != 0; });
    std::int32_t n = 0;
    const std::vector<std::int32_t> id = runs.numbers(&n);
    for (std::size_t r = 0; r < id.size(); ++r) {
      const auto& run = runs.runs()[r];
      std::int32_t* row = &comp.voxels[run.row * static_cast<std::size_t>(g.dims[0])];
      std::fill(row + run.i0, row + run.i1 + 1, id[r]);
    }
    if (count) *count = n;
    return comp;
  }
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

// The holes: background 6-connected components that never reach the grid's
// border. Only the mask's bounding box needs looking at: every voxel outside
// it reaches the border along an axis, and a path from inside the box to the
// border leaves the box through its own border voxels. So a hole is a
// background component of the box that touches none of the box's faces (a
// brain fills a third of a scan's grid: a fraction of the work). Components
// by runs (RunComponents); this runs on every outline mask of a scan.
Mask fill_holes(const Mask& mask) {
  const Grid3& g = mask.grid;
  Mask out = mask;
  const VoxelBox box = bounding_box_voxels(mask);
  if (box.empty) return out;
  const std::array<int, 3> dims{box.hi[0] - box.lo[0] + 1, box.hi[1] - box.lo[1] + 1, box.hi[2] - box.lo[2] + 1};
  const std::uint8_t* m = mask.voxels.data();
  const auto full = [&](int i, int j, int k) {
    return g.index(i + box.lo[0], j + box.lo[1], k + box.lo[2]);
  };
  RunComponents background(dims, [&](int i, int j, int k) { return m[full(i, j, k)] == 0; });
  const auto& runs = background.runs();
  std::vector<std::uint8_t> open(runs.size(), 0);
  for (std::size_t r = 0; r < runs.size(); ++r) {
    const auto& run = runs[r];
    const auto [j, k] = background.row_jk(run);
    if (run.i0 == 0 || run.i1 == dims[0] - 1 || j == 0 || j == dims[1] - 1 || k == 0 || k == dims[2] - 1)
      open[background.root(r)] = 1;
  }
  for (std::size_t r = 0; r < runs.size(); ++r) {
    if (open[background.root(r)]) continue;
    const auto& run = runs[r];
    const auto [j, k] = background.row_jk(run);
    std::fill_n(&out.voxels[full(run.i0, j, k)], run.i1 - run.i0 + 1, std::uint8_t{1});
  }
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
