#include "registration/intensity_lattice.h"

#include "core/parallel.h"

namespace brainshift::intensity {
namespace {

void include(VoxelBox& box, int i, int j, int k) {
  const int idx[3] = {i, j, k};
  for (int a = 0; a < 3; ++a) {
    box.lo[a] = box.empty ? idx[a] : std::min(box.lo[a], idx[a]);
    box.hi[a] = box.empty ? idx[a] : std::max(box.hi[a], idx[a]);
  }
  box.empty = false;
}

void include(VoxelBox& box, const VoxelBox& other) {
  if (other.empty) return;
  include(box, other.lo[0], other.lo[1], other.lo[2]);
  include(box, other.hi[0], other.hi[1], other.hi[2]);
}

// The first and last i of row (j, k) where inside(voxel index) holds, or false.
template <class Inside>
bool row_extent(const Grid3& g, int j, int k, Inside&& inside, int* first, int* last) {
  const std::size_t row = g.index(0, j, k);
  int i = 0;
  while (i < g.dims[0] && !inside(row + i)) ++i;
  if (i == g.dims[0]) return false;
  int e = g.dims[0] - 1;
  while (!inside(row + e)) --e;
  *first = i;
  *last = e;
  return true;
}

}  // namespace

Boxes find_boxes(const ImageF& sdf_mm, const LabelImage& labels, std::uint16_t background, double fade_mm) {
  const Grid3& g = sdf_mm.grid;
  const float fade = static_cast<float>(fade_mm);
  const float* sdf = sdf_mm.voxels.data();
  const std::uint16_t* label = labels.voxels.data();
  auto in_region = [&](std::size_t v) { return sdf[v] < fade; };
  auto foreign = [&](std::size_t v) { return sdf[v] <= 0.f && label[v] == background; };
  Boxes halves[2];
  on_two_halves(static_cast<std::size_t>(g.dims[2]), [&](std::size_t begin, std::size_t end, std::size_t half) {
    Boxes& b = halves[half];
    for (int k = static_cast<int>(begin); k < static_cast<int>(end); ++k)
      for (int j = 0; j < g.dims[1]; ++j) {
        int first, last;
        if (!row_extent(g, j, k, in_region, &first, &last)) continue;
        include(b.region, first, j, k);
        include(b.region, last, j, k);
        if (row_extent(g, j, k, foreign, &first, &last)) include(b.foreign, first, j, k), include(b.foreign, last, j, k);
      }
  });
  include(halves[0].region, halves[1].region);
  include(halves[0].foreign, halves[1].foreign);
  return halves[0];
}

}  // namespace brainshift::intensity
