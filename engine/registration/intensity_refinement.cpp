#include "registration/intensity_refinement.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <iomanip>
#include <limits>
#include <optional>
#include <sstream>

#include <nlohmann/json.hpp>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "image/interpolation.h"
#include "registration/linear_sampler.h"

namespace brainshift {
namespace {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using Vec3f = Eigen::Vector3f;

// fn(begin, end, half) on the two halves of [0, n), side by side when there
// is a second core (core/parallel.h). Always the same two partial results,
// so sums and the field do not depend on the number of cores.
template <class Fn>
void on_two_halves(std::size_t n, Fn&& fn) {
  const std::size_t mid = n / 2;
  parallel_halves(2, 1, [&](std::size_t begin, std::size_t end) {
    for (std::size_t h = begin; h < end; ++h) fn(h == 0 ? 0 : mid, h == 0 ? mid : n, h);
  });
}

double smoothstep(double t) {
  t = std::clamp(t, 0.0, 1.0);
  return t * t * (3.0 - 2.0 * t);
}

// ---- control lattice --------------------------------------------------------
// Nodes on the intraop voxel axes (so a voxel's cell is found without a
// matrix product), spacing_mm apart in every direction.
class Lattice {
 public:
  struct Cell {
    int base = 0;  // node of the cell's lowest corner
    float fx = 0, fy = 0, fz = 0;
  };

  Lattice(const VoxelBox& box, const Grid3& grid, double spacing_mm) : spacing_mm_(spacing_mm) {
    const Vec3 voxel_mm = grid.spacing_mm();
    for (int a = 0; a < 3; ++a) {
      origin_[a] = box.lo[a];
      step_[a] = spacing_mm / voxel_mm[a];
      n_[a] = static_cast<int>(std::floor((box.hi[a] - box.lo[a]) / step_[a])) + 2;
      lo_[a] = box.lo[a];
      extent_[a] = std::max(1, box.hi[a] - box.lo[a]);
    }
    coef_mm.assign(size(), Vec3::Zero());
  }

  std::size_t size() const { return static_cast<std::size_t>(n_[0]) * n_[1] * n_[2]; }
  int dim(int a) const { return n_[a]; }
  int node(int a, int b, int c) const { return a + n_[0] * (b + n_[1] * c); }
  double spacing_mm() const { return spacing_mm_; }

  Cell locate(double i, double j, double k) const {
    const double t[3] = {(i - origin_[0]) / step_[0], (j - origin_[1]) / step_[1], (k - origin_[2]) / step_[2]};
    int b[3];
    float f[3];
    for (int a = 0; a < 3; ++a) {
      b[a] = std::min(static_cast<int>(std::max(t[a], 0.0)), n_[a] - 2);  // floor for t >= 0
      f[a] = static_cast<float>(std::clamp(t[a] - b[a], 0.0, 1.0));
    }
    return {node(b[0], b[1], b[2]), f[0], f[1], f[2]};
  }

  // fn(node, weight) for the 8 corners of a cell (trilinear weights, sum 1).
  template <class Fn>
  void for_corners(const Cell& c, Fn&& fn) const {
    const int sy = n_[0], sz = n_[0] * n_[1];
    const double wx[2] = {1.0 - c.fx, c.fx}, wy[2] = {1.0 - c.fy, c.fy}, wz[2] = {1.0 - c.fz, c.fz};
    for (int dz = 0; dz < 2; ++dz)
      for (int dy = 0; dy < 2; ++dy)
        for (int dx = 0; dx < 2; ++dx) fn(c.base + dx + sy * dy + sz * dz, wx[dx] * wy[dy] * wz[dz]);
  }

  Vec3 value(const Cell& c) const {
    Vec3 v = Vec3::Zero();
    for_corners(c, [&](int n, double w) { v += w * coef_mm[n]; });
    return v;
  }

  // v along the voxel row (., j, k) at the lattice's x nodes, blended across
  // the other two axes once per row; row_weights interpolates along the row.
  void row(int j, int k, std::vector<Eigen::Vector3f>* line) const {
    const Cell c = locate(origin_[0], j, k);
    const int sy = n_[0], sz = n_[0] * n_[1];
    const double w[4] = {(1.0 - c.fy) * (1.0 - c.fz), c.fy * (1.0 - c.fz), (1.0 - c.fy) * c.fz, c.fy * c.fz};
    const int off[4] = {0, sy, sz, sy + sz};
    line->resize(static_cast<std::size_t>(n_[0]));
    for (int a = 0; a < n_[0]; ++a) {
      Vec3 v = Vec3::Zero();
      for (int q = 0; q < 4; ++q) v += w[q] * coef_mm[c.base + a + off[q]];
      (*line)[a] = v.cast<float>();
    }
  }
  // Cell and weight along x of every voxel i in [lo, hi] (the same for all rows).
  void row_weights(int lo, int hi, std::vector<int>* cell, std::vector<float>* frac) const {
    cell->clear();
    frac->clear();
    for (int i = lo; i <= hi; ++i) {
      const Cell c = locate(i, origin_[1], origin_[2]);
      cell->push_back(c.base);  // node (b, 0, 0) == b
      frac->push_back(c.fx);
    }
  }

  // Position in [-1, 1]^3 over the lattice's voxel box: the bias polynomial's
  // argument (well conditioned whatever the grid).
  Eigen::Vector3f normalised(int i, int j, int k) const {
    return {static_cast<float>(2.0 * (i - lo_[0]) / extent_[0] - 1.0),
            static_cast<float>(2.0 * (j - lo_[1]) / extent_[1] - 1.0),
            static_cast<float>(2.0 * (k - lo_[2]) / extent_[2] - 1.0)};
  }

  std::vector<Vec3> coef_mm;

 private:
  double spacing_mm_;
  Vec3 origin_, step_;
  std::array<int, 3> n_{}, lo_{}, extent_{};
};

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

// One pass over the grid: where v is used (within fade_mm of the brain
// region, whose distance is negative inside) and where background or cavity
// voxels lie inside the brain region (a resection cavity).
struct Boxes {
  VoxelBox region, foreign;
};

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

// ---- samples ------------------------------------------------------------------
struct Sample {
  Vec3 base_mm;            // x + u(x): the preop point before the correction
  // d(x + u)/dx at x: how a move of the intraop point moves the preop one.
  Eigen::Matrix3f jac = Eigen::Matrix3f::Identity();
  Eigen::Vector3f poly;    // normalised position, argument of the bias
  Lattice::Cell cell;
  float intensity = 0;     // intraop T1 at x
  float weight = 1;        // boundary down-weighting in [0, 1]
  float bias = 1;          // b(x), current fit
  float score = 0;         // weight * |grad P| when selected
  std::size_t voxel = 0;

  // The preop point once the intraop point has moved by v (the correction is
  // composed with the FEM's pull-back, see apply_correction), to first order.
  Vec3 preop_mm(const Vec3& v) const { return base_mm + jac.cast<double>() * v; }
};

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

struct Samples {
  std::vector<Sample> motion, bias;
  std::size_t candidates = 0;
  double density_per_mm3 = 0;  // motion samples per mm^3 of usable tissue
};

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

// ---- robust statistics ----------------------------------------------------------
double geman_mcclure_weight(double r, double scale) {
  const double t = r / scale;
  const double d = 1.0 + t * t;
  return 1.0 / (d * d);
}

double median(std::vector<double> values) {
  if (values.empty()) return 0;
  const auto mid = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
  std::nth_element(values.begin(), mid, values.end());
  return *mid;
}

// 1.4826 * median |r|: the spread of Gaussian noise, unmoved by outliers.
double robust_sigma(std::vector<double> abs_residuals) { return 1.4826 * median(std::move(abs_residuals)); }

// ---- intensity bias -----------------------------------------------------------------
int basis_size(int degree) { return (degree + 1) * (degree + 2) * (degree + 3) / 6; }

// Monomials x^a y^b z^c with a + b + c <= degree (at most 3).
void bias_basis(const Eigen::Vector3f& q, int degree, double* out) {
  double px[4] = {1, q.x(), 0, 0}, py[4] = {1, q.y(), 0, 0}, pz[4] = {1, q.z(), 0, 0};
  for (int e = 2; e <= 3; ++e) px[e] = px[e - 1] * px[1], py[e] = py[e - 1] * py[1], pz[e] = pz[e - 1] * pz[1];
  int n = 0;
  for (int total = 0; total <= degree; ++total)
    for (int a = total; a >= 0; --a)
      for (int b = total - a; b >= 0; --b) out[n++] = px[a] * py[b] * pz[total - a - b];
}

struct BiasModel {
  int degree = 0;
  Eigen::VectorXd coef = Eigen::VectorXd::Ones(1);  // of b(x)
  double offset = 0;                                 // d
  double explained = 0;  // share of the intensity variance the fit explains (weighted R^2)
  double at(const Eigen::Vector3f& q) const {
    double basis[20];
    bias_basis(q, degree, basis);
    double b = 0;
    for (int n = 0; n < coef.size(); ++n) b += coef[n] * basis[n];
    return b;
  }
};

// Weighted least squares of I ~ b(x) P + d (linear in b's coefficients and
// d; d = 0 without an offset). False when the system is singular or b is not
// clearly positive on the samples.
bool solve_bias(const std::vector<Sample>& s, const std::vector<double>& preop, const std::vector<double>& w,
                int degree, bool with_offset, BiasModel* out) {
  const int k = basis_size(degree), m1 = with_offset ? k + 1 : k;
  Eigen::MatrixXd normal = Eigen::MatrixXd::Zero(m1, m1);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(m1);
  double row[21];
  for (std::size_t n = 0; n < s.size(); ++n) {
    if (w[n] <= 0) continue;
    bias_basis(s[n].poly, degree, row);
    for (int a = 0; a < k; ++a) row[a] *= preop[n];
    if (with_offset) row[k] = 1.0;
    for (int a = 0; a < m1; ++a) {  // lower triangle, plain loops: sizes are tiny
      const double wa = w[n] * row[a];
      for (int b = 0; b <= a; ++b) normal(a, b) += wa * row[b];
      rhs[a] += wa * s[n].intensity;
    }
  }
  normal.triangularView<Eigen::StrictlyUpper>() = normal.transpose();
  Eigen::LDLT<Eigen::MatrixXd> ldlt(normal);
  if (ldlt.info() != Eigen::Success || ldlt.rcond() < 1e-12) return false;
  const Eigen::VectorXd x = ldlt.solve(rhs);
  BiasModel m;
  m.degree = degree;
  m.coef = x.head(k);
  m.offset = with_offset ? x[k] : 0.0;
  double b_min = std::numeric_limits<double>::infinity(), b_sum = 0;
  for (const auto& sample : s) {
    const double b = m.at(sample.poly);
    b_min = std::min(b_min, b);
    b_sum += b;
  }
  if (!(b_min > 0.2 * b_sum / static_cast<double>(s.size()))) return false;  // not a plausible coil bias
  *out = m;
  return true;
}

// Weighted R^2 of the fit: 1 - sum w r^2 / sum w (I - mean I)^2.
double explained_variance(const std::vector<Sample>& s, const std::vector<double>& preop,
                          const std::vector<double>& w, const BiasModel& m) {
  double sw = 0, swi = 0;
  for (std::size_t n = 0; n < s.size(); ++n) sw += w[n], swi += w[n] * s[n].intensity;
  if (!(sw > 0)) return 0;
  const double mean = swi / sw;
  double residual = 0, total = 0;
  for (std::size_t n = 0; n < s.size(); ++n) {
    const double r = s[n].intensity - (m.at(s[n].poly) * preop[n] + m.offset);
    residual += w[n] * r * r;
    total += w[n] * (s[n].intensity - mean) * (s[n].intensity - mean);
  }
  return total > 0 ? 1.0 - residual / total : 0.0;
}

// One robust (reweighted) fit of a given form; false when it fails.
bool robust_fit(const std::vector<Sample>& s, const std::vector<double>& p, const std::vector<double>& w, int degree,
                bool with_offset, double robust_scale, BiasModel* m) {
  std::vector<double> wn = w;
  bool ok = solve_bias(s, p, wn, degree, with_offset, m);
  for (int round = 0; ok && round < 2; ++round) {
    std::vector<double> r(s.size());
    std::vector<double> abs_r;
    for (std::size_t n = 0; n < s.size(); ++n) {
      r[n] = s[n].intensity - (m->at(s[n].poly) * p[n] + m->offset);
      if (w[n] > 0) abs_r.push_back(std::abs(r[n]));
    }
    const double scale = std::max(robust_scale * robust_sigma(abs_r), 1e-12);
    for (std::size_t n = 0; n < s.size(); ++n) wn[n] = w[n] * geman_mcclure_weight(r[n], scale);
    ok = solve_bias(s, p, wn, degree, with_offset, m);
  }
  return ok;
}

// The bias at the current correction: the degree drops when the data cannot
// support it, and when even a constant b with an offset is not determined (a
// tissue of nearly one intensity: b P and d cannot be told apart) a global
// scale alone is fitted. nullopt when no positive bias fits at all: the
// intraop intensities do not follow the preop T1's (another contrast).
std::optional<BiasModel> fit_bias(const std::vector<Sample>& s, const Lattice& lattice, const LinearSampler& preop,
                                  int degree, double robust_scale) {
  std::vector<double> p(s.size(), 0.0), w(s.size(), 0.0);
  for (std::size_t n = 0; n < s.size(); ++n) {
    double value;
    if (preop.sample(s[n].preop_mm(lattice.value(s[n].cell)), &value, nullptr)) p[n] = value, w[n] = s[n].weight;
  }
  BiasModel m;
  bool ok = false;
  for (int d = degree; d >= 0 && !ok; --d) ok = robust_fit(s, p, w, d, true, robust_scale, &m);
  if (!ok) ok = robust_fit(s, p, w, 0, false, robust_scale, &m);
  if (!ok) return std::nullopt;
  m.explained = explained_variance(s, p, w, m);
  return m;
}

std::string describe(const BiasModel& m) {
  std::ostringstream o;
  o << "I = b(x) P + d, b polynomial of degree " << m.degree << " (" << m.coef.size() << " terms), d "
    << m.offset;
  return o.str();
}

// ---- Gauss-Newton ---------------------------------------------------------------------
// Data term's gradient and lumped Hessian per node. Lumping (phi phi^T ->
// diag(phi), valid as the trilinear weights are >= 0 and sum to 1) gives a
// matrix above the true Gauss-Newton one, so a step never overshoots the
// linearised model; the gradient is exact, so the fixed point is the same.
struct NodeSystem {
  using Sym3 = Eigen::Matrix<double, 6, 1>;  // xx, xy, xz, yy, yz, zz
  std::vector<Sym3> hessian;
  std::vector<Vec3> gradient;
  double sum_r2 = 0;
  std::size_t used = 0;
  explicit NodeSystem(std::size_t n) : hessian(n, Sym3::Zero()), gradient(n, Vec3::Zero()) {}
  void add(const NodeSystem& o) {
    for (std::size_t n = 0; n < hessian.size(); ++n) hessian[n] += o.hessian[n], gradient[n] += o.gradient[n];
    sum_r2 += o.sum_r2;
    used += o.used;
  }
  Mat3 hessian_at(std::size_t n) const {
    const Sym3& h = hessian[n];
    Mat3 m;
    m << h[0], h[1], h[2], h[1], h[3], h[4], h[2], h[4], h[5];
    return m;
  }
};

struct DataTerm {
  const std::vector<Sample>& samples;
  const Lattice& lattice;
  const LinearSampler& preop;
  double offset = 0;  // bias model's d
  double sigma = 1;   // robust residual spread
  double robust_scale = 3;

  Vec3 point(std::size_t n) const { return samples[n].preop_mm(lattice.value(samples[n].cell)); }

  // fn(n, preop point) for every step-th sample of [begin, end).
  template <class Fn>
  void for_samples(std::size_t begin, std::size_t end, std::size_t step, Fn&& fn) const {
    for (std::size_t n = begin; n < end; n += step) fn(n, point(n));
  }

  void accumulate(std::size_t begin, std::size_t end, NodeSystem* out) const {
    const double scale = robust_scale * sigma;
    for_samples(begin, end, 1, [&](std::size_t n, const Vec3& y) {
      const Sample& s = samples[n];
      double value;
      Vec3 g;
      if (!preop.sample(y, &value, &g)) return;
      const double r = s.intensity - (s.bias * value + offset);
      out->sum_r2 += r * r;
      ++out->used;
      const double w = s.weight * geman_mcclure_weight(r, scale) / (sigma * sigma);
      const Vec3 dr = -static_cast<double>(s.bias) * (s.jac.cast<double>().transpose() * g);  // d r / d v
      NodeSystem::Sym3 h;
      h << dr[0] * dr[0], dr[0] * dr[1], dr[0] * dr[2], dr[1] * dr[1], dr[1] * dr[2], dr[2] * dr[2];
      h *= w;
      const Vec3 grad = w * r * dr;
      lattice.for_corners(s.cell, [&](int node, double phi) {
        out->hessian[node] += phi * h;
        out->gradient[node] += phi * grad;
      });
    });
  }

  NodeSystem evaluate() const {
    NodeSystem halves[2] = {NodeSystem(lattice.size()), NodeSystem(lattice.size())};
    on_two_halves(samples.size(), [&](std::size_t b, std::size_t e, std::size_t half) { accumulate(b, e, &halves[half]); });
    halves[0].add(halves[1]);
    return std::move(halves[0]);
  }

  // Robust spread and RMS of the residuals on every 4th sample: enough for a
  // median and a report, at a quarter of a pass.
  std::pair<double, double> residual_spread_and_rms() const {
    std::vector<double> abs_r;
    abs_r.reserve(samples.size() / 4 + 1);
    double sum2 = 0;
    for_samples(0, samples.size(), 4, [&](std::size_t n, const Vec3& y) {
      double value;
      if (!preop.sample(y, &value, nullptr)) return;
      abs_r.push_back(std::abs(samples[n].intensity - (samples[n].bias * value + offset)));
      sum2 += abs_r.back() * abs_r.back();
    });
    const double rms = abs_r.empty() ? 0.0 : std::sqrt(sum2 / static_cast<double>(abs_r.size()));
    return {robust_sigma(std::move(abs_r)), rms};
  }
};

// Membrane (graph Laplacian on the lattice's 6-neighbours) times alpha plus
// beta times the identity: the regulariser's Hessian.
void apply_prior(const Lattice& l, double alpha, double beta, const std::vector<Vec3>& x, std::vector<Vec3>* out) {
  out->resize(x.size());
  for (std::size_t n = 0; n < x.size(); ++n) (*out)[n] = beta * x[n];
  const int stride[3] = {1, l.dim(0), l.dim(0) * l.dim(1)};
  // Each edge once, along each axis: both ends get alpha (x_a - x_b).
  for (int axis = 0; axis < 3; ++axis)
    for (int c = 0; c < l.dim(2) - (axis == 2); ++c)
      for (int b = 0; b < l.dim(1) - (axis == 1); ++b)
        for (int a = 0; a < l.dim(0) - (axis == 0); ++a) {
          const int n = l.node(a, b, c), m = n + stride[axis];
          const Vec3 d = alpha * (x[n] - x[m]);
          (*out)[n] += d;
          (*out)[m] -= d;
        }
}

double dot(const std::vector<Vec3>& a, const std::vector<Vec3>& b) {
  double s = 0;
  for (std::size_t n = 0; n < a.size(); ++n) s += a[n].dot(b[n]);
  return s;
}

// (H + prior) step = -(gradient + prior * c), by conjugate gradients with the
// 3x3 node blocks as preconditioner. The lattice has a few thousand nodes:
// this costs far less than one pass over the samples.
std::vector<Vec3> gauss_newton_step(const NodeSystem& sys, const Lattice& l, double alpha, double beta) {
  const std::size_t n = l.size();
  std::vector<Vec3> prior_c, rhs(n), step(n, Vec3::Zero()), z(n), p, q;
  apply_prior(l, alpha, beta, l.coef_mm, &prior_c);
  for (std::size_t i = 0; i < n; ++i) rhs[i] = -(sys.gradient[i] + prior_c[i]);
  std::vector<Mat3> hessian(n), precond(n);
  for (std::size_t i = 0; i < n; ++i) {
    hessian[i] = sys.hessian_at(i);
    precond[i] = (hessian[i] + (6.0 * alpha + beta) * Mat3::Identity()).inverse();
  }
  auto apply = [&](const std::vector<Vec3>& x, std::vector<Vec3>* y) {
    apply_prior(l, alpha, beta, x, y);
    for (std::size_t i = 0; i < n; ++i) (*y)[i] += hessian[i] * x[i];
  };
  std::vector<Vec3> r = rhs;
  for (std::size_t i = 0; i < n; ++i) z[i] = precond[i] * r[i];
  p = z;
  double rz = dot(r, z);
  // A Gauss-Newton step only needs to be roughly right (the next one starts
  // from it): 1e-2 in the preconditioned residual norm, at most 6 rounds
  // (4, 6, 12 and 25 rounds give the same TRE on the phantom suite).
  const double stop = 1e-4 * std::max(rz, 1e-300);
  for (int it = 0; it < 6 && rz > stop; ++it) {
    apply(p, &q);
    const double pq = dot(p, q);
    if (!(pq > 0)) break;
    const double a = rz / pq;
    for (std::size_t i = 0; i < n; ++i) step[i] += a * p[i], r[i] -= a * q[i];
    for (std::size_t i = 0; i < n; ++i) z[i] = precond[i] * r[i];
    const double rz_next = dot(r, z);
    for (std::size_t i = 0; i < n; ++i) p[i] = z[i] + (rz_next / rz) * p[i];
    rz = rz_next;
  }
  return step;
}

// Applies the trust region and the bound on |v|; returns the largest move (mm).
double take_step(Lattice& l, const std::vector<Vec3>& step, const IntensityRefinementParameters& p) {
  double largest = 0;
  for (std::size_t i = 0; i < l.size(); ++i) {
    Vec3 d = step[i];
    if (d.norm() > p.max_step_mm) d *= p.max_step_mm / d.norm();
    Vec3 c = l.coef_mm[i] + d;
    if (c.norm() > p.max_correction_mm) c *= p.max_correction_mm / c.norm();
    largest = std::max(largest, (c - l.coef_mm[i]).norm());
    l.coef_mm[i] = c;
  }
  return largest;
}

void update_bias(std::vector<Sample>& samples, const BiasModel& m) {
  for (Sample& s : samples) s.bias = static_cast<float>(m.at(s.poly));
}

// ---- the dense correction -------------------------------------------------------
struct CorrectionStats {
  double max_mm = 0, sum_mm = 0;  // |u' - u| inside the brain region
  std::size_t voxels = 0;
};

// u at a continuous voxel index (trilinear, clamped to the grid; at least two
// voxels per axis, see check_inputs). Float: this runs for every voxel.
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
    for (std::size_t z = begin; z < end; ++z)
      for (int y = 0; y < composer.ny(); ++y)
        composer.row(box.lo[1] + y, box.lo[2] + static_cast<int>(z), &refined[z * slice + y * composer.nx()],
                     &halves[half]);
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

void check_inputs(const VectorImage3& u, const IntensityRefinementInput& in) {
  const Grid3& g = u.grid;
  if (g.dims[0] < 2 || g.dims[1] < 2 || g.dims[2] < 2 || u.vectors.size() != g.voxel_count())
    throw InputError("intensity refinement: the displacement field needs at least 2 voxels per axis");
  if (!in.intraop_t1.grid.same_geometry(g) || in.intraop_t1.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the intraop image is not on the field's grid");
  if (!in.intraop_labels.grid.same_geometry(g) || in.intraop_labels.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the intraop labels are not on the field's grid");
  if (!in.brain_sdf_mm.grid.same_geometry(g) || in.brain_sdf_mm.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the brain distance map is not on the field's grid");
  if (in.preop_t1.grid.voxel_count() == 0 || in.preop_t1.voxels.size() != in.preop_t1.grid.voxel_count())
    throw InputError("intensity refinement: the preop image is empty");
}

double median_intensity(const std::vector<Sample>& s) {
  std::vector<double> v;
  v.reserve(s.size());
  for (const Sample& x : s) v.push_back(x.intensity);
  return median(std::move(v));
}

// Why the image cannot be trusted to move the field, or "" when it can: the
// intensities must follow the preop T1's up to the bias model, and the model
// must explain a fair share of their variance (an unrelated image, or one
// dominated by noise, explains little and would only add noise to the field).
std::string untrusted_image(const std::optional<BiasModel>& bias, double min_explained) {
  if (!bias) return "the intraop intensities do not follow the preop T1 (no positive bias fits)";
  if (bias->explained < min_explained) {
    std::ostringstream o;
    o << std::fixed << std::setprecision(2) << "the bias model explains only " << bias->explained
      << " of the intraop intensity variance (minimum " << min_explained << ")";
    return o.str();
  }
  return "";
}

// The Gauss-Newton loop on the motion samples; returns the iterations done,
// 0 with report->skipped_reason set when the image is not trusted.
int optimise(Lattice& lattice, std::vector<Sample>& motion, const std::vector<Sample>& bias_samples,
             const LinearSampler& preop, const IntensityRefinementParameters& p, double density_per_mm3,
             double sigma_floor, IntensityRefinementReport* report) {
  const double h = lattice.spacing_mm();
  const double alpha = p.membrane_weight * density_per_mm3 * h;       // int |grad v|^2 dV on the lattice
  const double beta = p.shrink_weight_per_mm2 * density_per_mm3 * h * h * h;  // int |v|^2 dV
  DataTerm data{motion, lattice, preop, 0.0, 1.0, p.robust_scale};
  int it = 0;
  for (; it < p.iterations; ++it) {
    // The bias is fitted at v = 0 and re-fitted once half way, when the
    // edges are closer to aligned (the first fit stays if the second fails).
    if (it == 0 || it == p.iterations / 2) {
      const std::optional<BiasModel> bias = fit_bias(bias_samples, lattice, preop, p.bias_degree, p.robust_scale);
      if (it == 0) {
        report->explained_variance = bias ? bias->explained : 0.0;
        report->skipped_reason = untrusted_image(bias, p.min_explained_variance);
        if (!report->skipped_reason.empty()) return 0;
      }
      if (bias) {
        update_bias(motion, *bias);
        data.offset = bias->offset;
        report->bias_model = describe(*bias);
        report->explained_variance = bias->explained;
      }
      const auto [spread, rms] = data.residual_spread_and_rms();
      data.sigma = std::max(spread, sigma_floor);
      if (it == 0) report->rms_residual_before = rms;
    }
    const NodeSystem sys = data.evaluate();
    const double moved = take_step(lattice, gauss_newton_step(sys, lattice, alpha, beta), p);
    if (moved < p.convergence_mm) {
      ++it;
      break;
    }
  }
  report->rms_residual_after = data.residual_spread_and_rms().second;
  return it;
}

}  // namespace

std::string validation_error(const IntensityRefinementParameters& p) {
  if (!(p.lattice_spacing_mm >= 2 && p.lattice_spacing_mm <= 50)) return "lattice_spacing_mm must be in [2, 50]";
  if (p.iterations < 1 || p.iterations > 100) return "iterations must be in 1..100";
  if (!(p.convergence_mm > 0)) return "convergence_mm must be > 0";
  if (!(p.membrane_weight >= 0 && std::isfinite(p.membrane_weight))) return "membrane_weight must be >= 0";
  if (!(p.shrink_weight_per_mm2 > 0 && std::isfinite(p.shrink_weight_per_mm2)))
    return "shrink_weight_per_mm2 must be > 0 (without it a region without image edges is undetermined)";
  if (!(p.max_correction_mm > 0 && p.max_correction_mm <= 20)) return "max_correction_mm must be in (0, 20]";
  if (!(p.max_step_mm > 0)) return "max_step_mm must be > 0";
  if (!(p.sample_spacing_mm > 0)) return "sample_spacing_mm must be > 0";
  if (p.max_samples < 1000) return "max_samples must be >= 1000";
  if (!(p.boundary_margin_mm >= 0)) return "boundary_margin_mm must be >= 0";
  if (!(p.robust_scale > 0)) return "robust_scale must be > 0";
  if (p.bias_degree < 0 || p.bias_degree > 3) return "bias_degree must be in 0..3";
  if (!(p.outside_fade_mm >= 0)) return "outside_fade_mm must be >= 0";
  if (!(p.min_explained_variance >= 0 && p.min_explained_variance < 1)) return "min_explained_variance must be in [0, 1)";
  return "";
}

void validate(const IntensityRefinementParameters& p) {
  const std::string error = validation_error(p);
  if (!error.empty()) throw InputError("intensity refinement: " + error);
}

void to_json(nlohmann::json& j, const IntensityRefinementReport& r) {
  if (!r.applied) {
    j = {{"applied", false}, {"skipped", r.skipped_reason}};
    if (r.explained_variance != 0) j["explained_variance"] = r.explained_variance;
    return;
  }
  j = {{"applied", true},
       {"iterations", r.iterations},
       {"candidates", r.candidates},
       {"samples", r.samples},
       {"bias_samples", r.bias_samples},
       {"rms_residual_before", r.rms_residual_before},
       {"rms_residual_after", r.rms_residual_after},
       {"max_correction_mm", r.max_correction_mm},
       {"mean_correction_mm", r.mean_correction_mm},
       {"bias_model", r.bias_model},
       {"explained_variance", r.explained_variance},
       {"seconds", {{"sampling", r.sampling_seconds}, {"optimise", r.optimise_seconds}, {"apply", r.apply_seconds},
                    {"total", r.seconds}}}};
}

IntensityRefinementReport refine_with_intensity(VectorImage3& pullback_mm, const IntensityRefinementInput& input,
                                                const IntensityRefinementParameters& p) {
  Stopwatch clock;
  validate(p);
  check_inputs(pullback_mm, input);
  IntensityRefinementReport report;
  const Boxes boxes = find_boxes(input.brain_sdf_mm, input.intraop_labels, input.background_label, p.outside_fade_mm);
  if (boxes.region.empty) {
    report.skipped_reason = "no brain region in the intraop labels";
    return report;
  }
  Lattice lattice(boxes.region, pullback_mm.grid, p.lattice_spacing_mm);
  const LinearSampler preop(input.preop_t1);
  Samples samples = prepare_samples(pullback_mm, input, p, lattice, preop, boxes);
  report.candidates = samples.candidates;
  report.samples = samples.motion.size();
  report.bias_samples = samples.bias.size();
  if (samples.motion.size() < 1000) {
    report.skipped_reason = "too few tissue samples away from the boundary (" + std::to_string(report.samples) + ")";
    return report;
  }
  report.sampling_seconds = clock.seconds();
  const double median = std::max(median_intensity(samples.bias), 1e-12);
  report.iterations = optimise(lattice, samples.motion, samples.bias, preop, p, samples.density_per_mm3,
                               1e-3 * median, &report);
  if (!report.skipped_reason.empty()) return report;
  report.optimise_seconds = clock.seconds() - report.sampling_seconds;
  report.rms_residual_before /= median;
  report.rms_residual_after /= median;
  const CorrectionStats st = apply_correction(pullback_mm, lattice, input.brain_sdf_mm, boxes.region, p.outside_fade_mm);
  report.applied = true;
  report.max_correction_mm = st.max_mm;
  report.mean_correction_mm = st.voxels ? st.sum_mm / static_cast<double>(st.voxels) : 0.0;
  report.seconds = clock.seconds();
  report.apply_seconds = report.seconds - report.sampling_seconds - report.optimise_seconds;
  return report;
}

}  // namespace brainshift
