#include "registration/intensity_correction.h"

#include <algorithm>
#include <vector>

#include "core/parallel.h"
#include "core/smoothstep.h"
#include "image/interpolation.h"

namespace brainshift::intensity {
namespace {

// u at a continuous voxel index (trilinear, clamped to the grid; at least two
// voxels per axis, see check_inputs in intensity_refinement.cpp). Float: this
// runs for every voxel.
Vec3f field_at(const VectorImage3& u, const Vec3f& index) {
  Vec3f value;
  trilinear_sample<TrilinearEdge::kClamp, float>(u.grid, u.vectors.data(), index, &value);
  return value;
}

// The refined pull-back u'(x) = w(x) + u(x + w(x)), w = fade(x) v(x): the
// correction moves the intraop point before the FEM's pull-back maps it.
// Composed rather than added, the Jacobian determinants multiply
// (det(I + grad w) stays near 1 for a smooth correction of a few mm), so the
// correction cannot fold an element the FEM compressed strongly (det ~0.01
// under an 18 mm sinking) where an added one could. fade is 1 inside the
// brain region and falls smoothly to 0 at fade_mm outside it.
class Composer {
 public:
  Composer(const VectorImage3& u, const Lattice& l, const ImageF& sdf_mm, const VoxelBox& box, double fade_mm)
      : u_(u), lattice_(l), sdf_(sdf_mm), box_(box), fade_mm_(static_cast<float>(fade_mm)),
        index_per_mm_(u.grid.voxel_from_world().topLeftCorner<3, 3>().cast<float>()),
        nx_(box.hi[0] - box.lo[0] + 1), ny_(box.hi[1] - box.lo[1] + 1) {
    l.row_weights(box.lo[0], box.hi[0], &cell_, &frac_);
  }

  // u' over the box's row (j, k) into out (nx values; u itself outside the fade).
  void row(int j, int k, Vec3f* out, CorrectionStats* st) const {
    lattice_.row(j, k, &line_);
    const std::size_t first = u_.grid.index(box_.lo[0], j, k);
    const Vec3f jk(0.f, static_cast<float>(j), static_cast<float>(k));
    for (int x = 0; x < nx_; ++x) {
      const Vec3f& old = u_.vectors[first + x];
      const float d = sdf_.voxels[first + x];
      const float fade = d <= 0.f ? 1.f : fade_mm_ > 0.f ? 1.f - static_cast<float>(smoothstep(d / fade_mm_)) : 0.f;
      if (fade <= 0.f) {
        out[x] = old;
        continue;
      }
      const Vec3f& a = line_[cell_[x]];
      const Vec3f w = fade * (a + frac_[x] * (line_[cell_[x] + 1] - a));
      out[x] = w + field_at(u_, jk + Vec3f(static_cast<float>(box_.lo[0] + x), 0.f, 0.f) + index_per_mm_ * w);
      if (d > 0.f) continue;
      const double change = (out[x] - old).norm();
      st->max_mm = std::max(st->max_mm, change);
      st->sum_mm += change;
      ++st->voxels;
    }
  }

  int nx() const { return nx_; }
  int ny() const { return ny_; }

 private:
  const VectorImage3& u_;
  const Lattice& lattice_;
  const ImageF& sdf_;
  const VoxelBox& box_;
  float fade_mm_;
  Eigen::Matrix3f index_per_mm_;
  int nx_, ny_;
  std::vector<int> cell_;
  std::vector<float> frac_;
  mutable std::vector<Vec3f> line_;  // one Composer per thread
};

}  // namespace

CorrectionStats apply_correction(VectorImage3& u, const Lattice& l, const ImageF& sdf_mm, const VoxelBox& box,
                                 double fade_mm) {
  const int nz = box.hi[2] - box.lo[2] + 1;
  // Written beside u, not into it: u' reads u around each voxel.
  const Composer probe(u, l, sdf_mm, box, fade_mm);
  const std::size_t slice = static_cast<std::size_t>(probe.nx()) * probe.ny();
  std::vector<Vec3f> refined(slice * nz);
  CorrectionStats halves[2];
  on_two_halves(static_cast<std::size_t>(nz), [&](std::size_t begin, std::size_t end, std::size_t half) {
    const Composer composer(u, l, sdf_mm, box, fade_mm);
    // Kept here and stored once: the two halves' stats share a cache line.
    CorrectionStats stats;
    for (std::size_t z = begin; z < end; ++z)
      for (int y = 0; y < composer.ny(); ++y)
        composer.row(box.lo[1] + y, box.lo[2] + static_cast<int>(z), &refined[z * slice + y * composer.nx()], &stats);
    halves[half] = stats;
  });
  on_two_halves(static_cast<std::size_t>(nz), [&](std::size_t begin, std::size_t end, std::size_t) {
    for (std::size_t z = begin; z < end; ++z)
      for (int y = 0; y < probe.ny(); ++y)
        std::copy_n(&refined[z * slice + y * probe.nx()], probe.nx(),
                    &u.vectors[u.grid.index(box.lo[0], box.lo[1] + y, box.lo[2] + static_cast<int>(z))]);
  });
  halves[0].max_mm = std::max(halves[0].max_mm, halves[1].max_mm);
  halves[0].sum_mm += halves[1].sum_mm;
  halves[0].voxels += halves[1].voxels;
  return halves[0];
}

}  // namespace brainshift::intensity
