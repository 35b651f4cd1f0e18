#include "field/unfold.h"

#include <algorithm>
#include <vector>

#include "core/errors.h"
#include "field/metrics.h"

namespace brainshift {
namespace {

std::vector<std::size_t> bad_voxels(const VectorImage3& f, const Mask& region, double floor,
                                    const std::vector<std::size_t>* candidates) {
  const Grid3& g = f.grid;
  std::vector<std::size_t> bad;
  auto test = [&](std::size_t v) {
    if (!region.voxels[v]) return;
    const int i = static_cast<int>(v % g.dims[0]);
    const int j = static_cast<int>((v / g.dims[0]) % g.dims[1]);
    const int k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    if (jacobian_determinant_at(f, i, j, k) < floor) bad.push_back(v);
  };
  if (candidates) {
    for (std::size_t v : *candidates) test(v);
  } else {
    for (std::size_t v = 0; v < g.voxel_count(); ++v) test(v);
  }
  return bad;
}

// Voxels within radius (box) of any bad voxel, without duplicates.
std::vector<std::size_t> neighbourhood(const Grid3& g, const std::vector<std::size_t>& bad, int radius,
                                       std::vector<char>& mark) {
  std::vector<std::size_t> out;
  for (std::size_t v : bad) {
    const int i = static_cast<int>(v % g.dims[0]);
    const int j = static_cast<int>((v / g.dims[0]) % g.dims[1]);
    const int k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    for (int dk = -radius; dk <= radius; ++dk)
      for (int dj = -radius; dj <= radius; ++dj)
        for (int di = -radius; di <= radius; ++di) {
          if (!g.contains(i + di, j + dj, k + dk)) continue;
          const std::size_t w = g.index(i + di, j + dj, k + dk);
          if (!mark[w]) {
            mark[w] = 1;
            out.push_back(w);
          }
        }
  }
  for (std::size_t w : out) mark[w] = 0;
  return out;
}

// One Jacobi pass of 3x3x3 averaging over the given voxels.
double smooth(VectorImage3& f, const std::vector<std::size_t>& voxels) {
  const Grid3& g = f.grid;
  std::vector<Eigen::Vector3f> next(voxels.size());
  for (std::size_t n = 0; n < voxels.size(); ++n) {
    const std::size_t v = voxels[n];
    const int i = static_cast<int>(v % g.dims[0]);
    const int j = static_cast<int>((v / g.dims[0]) % g.dims[1]);
    const int k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    Eigen::Vector3f sum = Eigen::Vector3f::Zero();
    int count = 0;
    for (int dk = -1; dk <= 1; ++dk)
      for (int dj = -1; dj <= 1; ++dj)
        for (int di = -1; di <= 1; ++di)
          if (g.contains(i + di, j + dj, k + dk)) {
            sum += f.vectors[g.index(i + di, j + dj, k + dk)];
            ++count;
          }
    next[n] = sum / static_cast<float>(count);
  }
  double max_step = 0;
  for (std::size_t n = 0; n < voxels.size(); ++n) {
    max_step = std::max(max_step, static_cast<double>((next[n] - f.vectors[voxels[n]]).norm()));
    f.vectors[voxels[n]] = next[n];
  }
  return max_step;
}

}  // namespace

bool unfold_field(VectorImage3& field, const Mask& region, const UnfoldParameters& p, UnfoldStats* stats) {
  if (!field.grid.same_geometry(region.grid)) throw InputError("unfold_field: region and field grids differ");
  if (p.max_rounds < 0 || p.radius_voxels < 1) throw InputError("unfold_field: bad parameters");
  UnfoldStats s;
  const std::vector<Eigen::Vector3f> original_vectors = field.vectors;
  std::vector<char> mark(field.grid.voxel_count(), 0), changed(field.grid.voxel_count(), 0);
  std::vector<std::size_t> bad = bad_voxels(field, region, p.min_determinant, nullptr);
  s.bad_voxels_before = bad.size();
  while (!bad.empty() && s.rounds < p.max_rounds) {
    const std::vector<std::size_t> zone = neighbourhood(field.grid, bad, p.radius_voxels, mark);
    smooth(field, zone);
    for (std::size_t v : zone) changed[v] = 1;
    ++s.rounds;
    // Smoothing only changes determinants within one voxel of the zone.
    const std::vector<std::size_t> recheck = neighbourhood(field.grid, zone, 1, mark);
    bad = bad_voxels(field, region, p.min_determinant, &recheck);
  }
  s.bad_voxels_after = bad.size();
  for (std::size_t v = 0; v < changed.size(); ++v)
    if (changed[v]) {
      ++s.changed_voxels;
      s.max_change_mm = std::max(s.max_change_mm,
                                 static_cast<double>((field.vectors[v] - original_vectors[v]).norm()));
    }
  if (stats) *stats = s;
  return bad.empty();
}

}  // namespace brainshift
