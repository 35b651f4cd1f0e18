#include "registration/intensity_samples.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>

#include "core/parallel.h"
#include "core/smoothstep.h"
#include "image/distance_map.h"
#include "image/image_stats.h"

namespace brainshift::intensity {
namespace {

// d(x + u(x))/dx at a voxel: central differences (one-sided at the grid's
// faces) in index space, mapped to world mm.
Mat3 pullback_jacobian(const VectorImage3& u, const Mat3& index_per_mm, int i, int j, int k) {
  Mat3 d_index;  // column a: du / d(index a)
  const int at[3] = {i, j, k};
  for (int a = 0; a < 3; ++a) {
    int lo[3] = {i, j, k}, hi[3] = {i, j, k};
    lo[a] = std::max(0, at[a] - 1);
    hi[a] = std::min(u.grid.dims[a] - 1, at[a] + 1);
    const Eigen::Vector3f diff = u.vectors[u.grid.index(hi[0], hi[1], hi[2])] - u.vectors[u.grid.index(lo[0], lo[1], lo[2])];
    d_index.col(a) = hi[a] > lo[a] ? Vec3(diff.cast<double>() / (hi[a] - lo[a])) : Vec3::Zero();
  }
  return Mat3::Identity() + d_index * index_per_mm;
}

// Distance (mm) from the background/cavity voxels inside the brain region (a
// resection cavity): computed on their bounding box only, as the ventricles'
// map in boundary_samples.cpp; +inf where there are none.
class InternalForeignDistance {
 public:
  InternalForeignDistance(const LabelImage& labels, const ImageF& sdf_mm, std::uint16_t background,
                          const VoxelBox& foreign_box, double margin_mm) {
    if (foreign_box.empty) return;
    box_ = grow_box(foreign_box, labels.grid, margin_mm);
    Grid3 crop = labels.grid;
    for (int a = 0; a < 3; ++a) crop.dims[a] = box_.hi[a] - box_.lo[a] + 1;
    crop.world_from_voxel.topRightCorner<3, 1>() = labels.grid.world_mm(box_.lo[0], box_.lo[1], box_.lo[2]);
    Mask foreign(crop, 0);
    for (int k = 0; k < crop.dims[2]; ++k)
      for (int j = 0; j < crop.dims[1]; ++j)
        for (int i = 0; i < crop.dims[0]; ++i) {
          const std::size_t v = labels.grid.index(i + box_.lo[0], j + box_.lo[1], k + box_.lo[2]);
          foreign.at(i, j, k) = labels.voxels[v] == background && sdf_mm.voxels[v] <= 0.f;
        }
    map_ = distance_to_mask_mm(foreign);
  }
  double at(int i, int j, int k) const {
    if (box_.empty || i < box_.lo[0] || j < box_.lo[1] || k < box_.lo[2] || i > box_.hi[0] || j > box_.hi[1] ||
        k > box_.hi[2])
      return std::numeric_limits<double>::infinity();
    return map_.at(i - box_.lo[0], j - box_.lo[1], k - box_.lo[2]);
  }

 private:
  VoxelBox box_;
  ImageF map_;
};

struct SamplingContext {
  const VectorImage3& u;
  const IntensityRefinementInput& in;
  const IntensityRefinementParameters& p;
  const Lattice& lattice;
  const LinearSampler& preop;
  const InternalForeignDistance& foreign;
  std::vector<std::uint8_t> tissue;  // by label value
  std::array<int, 3> stride{};
  VoxelBox box;
  Mat3 index_per_mm = Mat3::Identity();  // d(voxel index)/d(world mm)
};

// A usable tissue voxel and how much it says: only these few bytes are kept
// for the ~170k candidates, full samples for the ones selected.
struct Candidate {
  std::uint32_t voxel = 0;
  float weight = 0;  // boundary down-weighting in (0, 1]
  float score = 0;   // weight * |grad P| at x + u(x)
};

// The candidate at voxel (i,j,k), or false when it is not usable tissue.
bool make_candidate(const SamplingContext& ctx, int i, int j, int k, Candidate* c) {
  const Grid3& g = ctx.u.grid;
  const std::size_t v = g.index(i, j, k);
  if (!ctx.tissue[ctx.in.intraop_labels.voxels[v]] || !std::isfinite(ctx.in.intraop_t1.voxels[v])) return false;
  const double outer_mm = -ctx.in.brain_sdf_mm.voxels[v];
  const double d_mm = std::min(outer_mm, ctx.foreign.at(i, j, k));
  const double half = 0.5 * ctx.p.boundary_margin_mm;
  const double weight = half > 0 ? smoothstep((d_mm - half) / half) : (d_mm > 0 ? 1.0 : 0.0);
  if (weight <= 0) return false;
  double value;
  Vec3 grad;
  if (!ctx.preop.sample(g.world_mm(i, j, k) + ctx.u.vectors[v].cast<double>(), &value, &grad)) return false;
  *c = {static_cast<std::uint32_t>(v), static_cast<float>(weight), static_cast<float>(weight * grad.norm())};
  return true;
}

// Candidates on a sparse grid over the lattice box, in voxel order whatever
// the number of threads.
std::vector<Candidate> collect_candidates(const SamplingContext& ctx) {
  std::vector<int> slices;
  for (int k = ctx.box.lo[2]; k <= ctx.box.hi[2]; k += ctx.stride[2]) slices.push_back(k);
  std::vector<Candidate> halves[2];
  on_two_halves(slices.size(), [&](std::size_t begin, std::size_t end, std::size_t half) {
    std::vector<Candidate>& out = halves[half];
    Candidate c;
    for (std::size_t n = begin; n < end; ++n)
      for (int j = ctx.box.lo[1]; j <= ctx.box.hi[1]; j += ctx.stride[1])
        for (int i = ctx.box.lo[0]; i <= ctx.box.hi[0]; i += ctx.stride[0])
          if (make_candidate(ctx, i, j, slices[n], &c)) out.push_back(c);
  });
  halves[0].insert(halves[0].end(), halves[1].begin(), halves[1].end());
  return std::move(halves[0]);
}

Sample make_sample(const SamplingContext& ctx, const Candidate& c) {
  const Grid3& g = ctx.u.grid;
  const int i = static_cast<int>(c.voxel % g.dims[0]), j = static_cast<int>((c.voxel / g.dims[0]) % g.dims[1]),
            k = static_cast<int>(c.voxel / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
  Sample s;
  s.base_mm = g.world_mm(i, j, k) + ctx.u.vectors[c.voxel].cast<double>();
  s.jac = pullback_jacobian(ctx.u, ctx.index_per_mm, i, j, k).cast<float>();
  s.poly = ctx.lattice.normalised(i, j, k);
  s.cell = ctx.lattice.locate(i, j, k);
  s.intensity = ctx.in.intraop_t1.voxels[c.voxel];
  s.weight = c.weight;
  s.score = c.score;
  s.voxel = c.voxel;
  return s;
}

// The strongest-gradient candidates drive the motion (flat tissue says
// nothing about where it moved); an even spread of all candidates fits the
// bias, which must not lean toward edges that are still misaligned (a fifth
// as many: the bias has at most 21 unknowns).
void select_samples(const SamplingContext& ctx, const std::vector<Candidate>& candidates, std::size_t max_samples,
                    std::vector<Sample>* motion, std::vector<Sample>* bias) {
  const std::size_t bias_count = std::max<std::size_t>(1, max_samples / 5);
  const std::size_t every = std::max<std::size_t>(1, (candidates.size() + bias_count - 1) / bias_count);
  for (std::size_t n = 0; n < candidates.size(); n += every) bias->push_back(make_sample(ctx, candidates[n]));
  std::vector<std::uint8_t> keep(candidates.size(), 1);
  if (candidates.size() > max_samples) {
    std::vector<std::pair<float, std::size_t>> order(candidates.size());  // (-score, index): strongest first
    for (std::size_t n = 0; n < candidates.size(); ++n) order[n] = {-candidates[n].score, n};
    std::nth_element(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(max_samples), order.end());
    std::fill(keep.begin(), keep.end(), 0);
    for (std::size_t n = 0; n < max_samples; ++n) keep[order[n].second] = 1;
  }
  motion->reserve(std::min(max_samples, candidates.size()));
  for (std::size_t n = 0; n < candidates.size(); ++n)  // in voxel order: u is read in sequence
    if (keep[n]) motion->push_back(make_sample(ctx, candidates[n]));
}

}  // namespace

Samples prepare_samples(const VectorImage3& u, const IntensityRefinementInput& in,
                        const IntensityRefinementParameters& p, const Lattice& lattice, const LinearSampler& preop,
                        const Boxes& boxes) {
  const Grid3& grid = u.grid;
  const InternalForeignDistance foreign(in.intraop_labels, in.brain_sdf_mm, in.background_label, boxes.foreign,
                                        p.boundary_margin_mm);
  SamplingContext ctx{u, in, p, lattice, preop, foreign, std::vector<std::uint8_t>(65536, 0), {}, boxes.region,
                      grid.voxel_from_world().topLeftCorner<3, 3>()};
  for (auto l : in.tissue_labels) ctx.tissue[l] = 1;
  const Vec3 voxel_mm = grid.spacing_mm();
  for (int a = 0; a < 3; ++a) ctx.stride[a] = std::max(1, static_cast<int>(std::lround(p.sample_spacing_mm / voxel_mm[a])));
  const std::vector<Candidate> candidates = collect_candidates(ctx);
  Samples out;
  out.candidates = candidates.size();
  select_samples(ctx, candidates, p.max_samples, &out.motion, &out.bias);
  const double voxel_mm3 = std::abs(grid.world_from_voxel.topLeftCorner<3, 3>().determinant());
  const double tissue_mm3 = static_cast<double>(candidates.size()) * ctx.stride[0] * ctx.stride[1] * ctx.stride[2] * voxel_mm3;
  out.density_per_mm3 = tissue_mm3 > 0 ? static_cast<double>(out.motion.size()) / tissue_mm3 : 0.0;
  return out;
}

}  // namespace brainshift::intensity
