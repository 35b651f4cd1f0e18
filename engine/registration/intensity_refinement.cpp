#include "registration/intensity_refinement.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <sstream>

#include <nlohmann/json.hpp>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "registration/linear_sampler.h"

namespace brainshift {
namespace {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;

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
      b[a] = std::clamp(static_cast<int>(std::floor(t[a])), 0, n_[a] - 2);
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

// Voxels within fade_mm of the brain region (negative distance inside).
VoxelBox region_box(const ImageF& sdf_mm, double fade_mm) {
  VoxelBox box;
  const auto& d = sdf_mm.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        if (!(sdf_mm.voxels[sdf_mm.grid.index(i, j, k)] < fade_mm)) continue;
        const int idx[3] = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          box.lo[a] = box.empty ? idx[a] : std::min(box.lo[a], idx[a]);
          box.hi[a] = box.empty ? idx[a] : std::max(box.hi[a], idx[a]);
        }
        box.empty = false;
      }
  return box;
}

// ---- samples ------------------------------------------------------------------
struct Sample {
  Vec3 base_mm;            // x + u(x): the preop point before the correction
  Eigen::Vector3f poly;    // normalised position, argument of the bias
  Lattice::Cell cell;
  float intensity = 0;     // intraop T1 at x
  float weight = 1;        // boundary down-weighting in [0, 1]
  float bias = 1;          // b(x), current fit
  float score = 0;         // selection: weight * |grad P|
  std::size_t voxel = 0;
};

// Distance (mm) from the background/cavity voxels inside the brain region (a
// resection cavity): computed on their bounding box only, as the ventricles'
// map in boundary_samples.cpp; +inf where there are none.
class InternalForeignDistance {
 public:
  InternalForeignDistance(const LabelImage& labels, const ImageF& sdf_mm, std::uint16_t background,
                          double margin_mm) {
    Mask foreign(labels.grid, 0);
    bool any = false;
    for (std::size_t v = 0; v < foreign.voxels.size(); ++v)
      if (labels.voxels[v] == background && sdf_mm.voxels[v] <= 0.f) foreign.voxels[v] = 1, any = true;
    if (!any) return;
    box_ = grow_box(bounding_box_voxels(foreign), foreign.grid, margin_mm);
    map_ = distance_to_mask_mm(crop_to_box(foreign, box_));
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
};

// One candidate at voxel (i,j,k), or false when it is not usable tissue.
bool make_candidate(const SamplingContext& ctx, int i, int j, int k, Sample* s) {
  const Grid3& g = ctx.u.grid;
  const std::size_t v = g.index(i, j, k);
  const float intensity = ctx.in.intraop_t1.voxels[v];
  if (!ctx.tissue[ctx.in.intraop_labels.voxels[v]] || !std::isfinite(intensity)) return false;
  const double outer_mm = -ctx.in.brain_sdf_mm.voxels[v];
  const double d_mm = std::min(outer_mm, ctx.foreign.at(i, j, k));
  const double half = 0.5 * ctx.p.boundary_margin_mm;
  const double weight = half > 0 ? smoothstep((d_mm - half) / half) : (d_mm > 0 ? 1.0 : 0.0);
  if (weight <= 0) return false;
  s->base_mm = g.world_mm(i, j, k) + ctx.u.vectors[v].cast<double>();
  double value;
  Vec3 grad;
  if (!ctx.preop.sample(s->base_mm, &value, &grad)) return false;
  s->poly = ctx.lattice.normalised(i, j, k);
  s->cell = ctx.lattice.locate(i, j, k);
  s->intensity = intensity;
  s->weight = static_cast<float>(weight);
  s->score = static_cast<float>(weight * grad.norm());
  s->voxel = v;
  return true;
}

// Candidates on a sparse grid over the lattice box, in voxel order whatever
// the number of threads.
std::vector<Sample> collect_candidates(const SamplingContext& ctx) {
  std::vector<int> slices;
  for (int k = ctx.box.lo[2]; k <= ctx.box.hi[2]; k += ctx.stride[2]) slices.push_back(k);
  std::vector<Sample> halves[2];
  parallel_halves(slices.size(), 4, [&](std::size_t begin, std::size_t end) {
    std::vector<Sample>& out = halves[begin == 0 ? 0 : 1];
    Sample s;
    for (std::size_t n = begin; n < end; ++n)
      for (int j = ctx.box.lo[1]; j <= ctx.box.hi[1]; j += ctx.stride[1])
        for (int i = ctx.box.lo[0]; i <= ctx.box.hi[0]; i += ctx.stride[0])
          if (make_candidate(ctx, i, j, slices[n], &s)) out.push_back(s);
  });
  halves[0].insert(halves[0].end(), halves[1].begin(), halves[1].end());
  return std::move(halves[0]);
}

// The strongest-gradient candidates drive the motion (flat tissue says
// nothing about where it moved); an even spread of all candidates fits the
// bias, which must not lean toward edges that are still misaligned.
void select_samples(std::vector<Sample> candidates, std::size_t max_samples, std::vector<Sample>* motion,
                    std::vector<Sample>* bias) {
  const std::size_t every = std::max<std::size_t>(1, (2 * candidates.size() + max_samples - 1) / std::max<std::size_t>(1, max_samples));
  for (std::size_t n = 0; n < candidates.size(); n += every) bias->push_back(candidates[n]);
  if (candidates.size() > max_samples) {
    std::nth_element(candidates.begin(), candidates.begin() + static_cast<std::ptrdiff_t>(max_samples),
                     candidates.end(), [](const Sample& a, const Sample& b) {
                       return a.score != b.score ? a.score > b.score : a.voxel < b.voxel;
                     });
    candidates.resize(max_samples);
    std::sort(candidates.begin(), candidates.end(), [](const Sample& a, const Sample& b) { return a.voxel < b.voxel; });
  }
  *motion = std::move(candidates);
}

// ---- robust statistics ----------------------------------------------------------
double geman_mcclure_weight(double r, double scale) {
  const double t = r / scale;
  const double d = 1.0 + t * t;
  return 1.0 / (d * d);
}

// 1.4826 * median |r|: the spread of Gaussian noise, unmoved by outliers.
double robust_sigma(std::vector<double> abs_residuals) {
  if (abs_residuals.empty()) return 0;
  const auto mid = abs_residuals.begin() + static_cast<std::ptrdiff_t>(abs_residuals.size() / 2);
  std::nth_element(abs_residuals.begin(), mid, abs_residuals.end());
  return 1.4826 * *mid;
}

// ---- intensity bias -----------------------------------------------------------------
int basis_size(int degree) { return (degree + 1) * (degree + 2) * (degree + 3) / 6; }

// Monomials x^a y^b z^c with a + b + c <= degree.
void bias_basis(const Eigen::Vector3f& q, int degree, double* out) {
  int n = 0;
  for (int total = 0; total <= degree; ++total)
    for (int a = total; a >= 0; --a)
      for (int b = total - a; b >= 0; --b) {
        const int c = total - a - b;
        out[n++] = std::pow(q.x(), a) * std::pow(q.y(), b) * std::pow(q.z(), c);
      }
}

struct BiasModel {
  int degree = 0;
  Eigen::VectorXd coef = Eigen::VectorXd::Ones(1);  // of b(x)
  double offset = 0;                                 // d
  double at(const Eigen::Vector3f& q) const {
    double basis[20];
    bias_basis(q, degree, basis);
    double b = 0;
    for (int n = 0; n < coef.size(); ++n) b += coef[n] * basis[n];
    return b;
  }
};

// Weighted least squares of I ~ b(x) P + d (linear in b's coefficients and d).
// False when the system is singular or b is not clearly positive on the samples.
bool solve_bias(const std::vector<Sample>& s, const std::vector<double>& preop, const std::vector<double>& w,
                int degree, BiasModel* out) {
  const int k = basis_size(degree);
  Eigen::MatrixXd normal = Eigen::MatrixXd::Zero(k + 1, k + 1);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(k + 1);
  Eigen::VectorXd row(k + 1);
  for (std::size_t n = 0; n < s.size(); ++n) {
    if (w[n] <= 0) continue;
    bias_basis(s[n].poly, degree, row.data());
    row.head(k) *= preop[n];
    row[k] = 1.0;
    normal.selfadjointView<Eigen::Lower>().rankUpdate(row, w[n]);
    rhs += w[n] * s[n].intensity * row;
  }
  normal.triangularView<Eigen::Upper>() = normal.transpose();
  Eigen::LDLT<Eigen::MatrixXd> ldlt(normal);
  if (ldlt.info() != Eigen::Success || ldlt.rcond() < 1e-12) return false;
  const Eigen::VectorXd x = ldlt.solve(rhs);
  BiasModel m;
  m.degree = degree;
  m.coef = x.head(k);
  m.offset = x[k];
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

// Robust (reweighted) fit at the current correction; the degree drops when
// the data cannot support it.
BiasModel fit_bias(const std::vector<Sample>& s, const Lattice& lattice, const LinearSampler& preop,
                   int degree, double robust_scale) {
  std::vector<double> p(s.size(), 0.0), w(s.size(), 0.0);
  for (std::size_t n = 0; n < s.size(); ++n) {
    double value;
    if (preop.sample(s[n].base_mm + lattice.value(s[n].cell), &value, nullptr)) p[n] = value, w[n] = s[n].weight;
  }
  for (int d = degree; d >= 0; --d) {
    BiasModel m;
    std::vector<double> wn = w;
    bool ok = solve_bias(s, p, wn, d, &m);
    for (int round = 0; ok && round < 2; ++round) {
      std::vector<double> r(s.size());
      std::vector<double> abs_r;
      for (std::size_t n = 0; n < s.size(); ++n) {
        r[n] = s[n].intensity - (m.at(s[n].poly) * p[n] + m.offset);
        if (w[n] > 0) abs_r.push_back(std::abs(r[n]));
      }
      const double scale = std::max(robust_scale * robust_sigma(abs_r), 1e-12);
      for (std::size_t n = 0; n < s.size(); ++n) wn[n] = w[n] * geman_mcclure_weight(r[n], scale);
      ok = solve_bias(s, p, wn, d, &m);
    }
    if (ok) return m;
  }
  return BiasModel{};  // b = 1, d = 0: no evidence for anything else
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
  std::vector<Mat3> hessian;
  std::vector<Vec3> gradient;
  double sum_r2 = 0;
  std::size_t used = 0;
  explicit NodeSystem(std::size_t n) : hessian(n, Mat3::Zero()), gradient(n, Vec3::Zero()) {}
  void add(const NodeSystem& o) {
    for (std::size_t n = 0; n < hessian.size(); ++n) hessian[n] += o.hessian[n], gradient[n] += o.gradient[n];
    sum_r2 += o.sum_r2;
    used += o.used;
  }
};

struct DataTerm {
  const std::vector<Sample>& samples;
  const Lattice& lattice;
  const LinearSampler& preop;
  double offset = 0;  // bias model's d
  double sigma = 1;   // robust residual spread
  double robust_scale = 3;

  void accumulate(std::size_t begin, std::size_t end, NodeSystem* out) const {
    const double scale = robust_scale * sigma;
    for (std::size_t n = begin; n < end; ++n) {
      const Sample& s = samples[n];
      double value;
      Vec3 g;
      if (!preop.sample(s.base_mm + lattice.value(s.cell), &value, &g)) continue;
      const double r = s.intensity - (s.bias * value + offset);
      out->sum_r2 += r * r;
      ++out->used;
      const double w = s.weight * geman_mcclure_weight(r, scale) / (sigma * sigma);
      const Vec3 dr = -static_cast<double>(s.bias) * g;  // d r / d v
      const Mat3 h = w * dr * dr.transpose();
      const Vec3 grad = w * r * dr;
      lattice.for_corners(s.cell, [&](int node, double phi) {
        out->hessian[node] += phi * h;
        out->gradient[node] += phi * grad;
      });
    }
  }

  NodeSystem evaluate() const {
    NodeSystem halves[2] = {NodeSystem(lattice.size()), NodeSystem(lattice.size())};
    parallel_halves(samples.size(), 4096, [&](std::size_t b, std::size_t e) { accumulate(b, e, &halves[b == 0 ? 0 : 1]); });
    halves[0].add(halves[1]);
    return std::move(halves[0]);
  }

  std::vector<double> abs_residuals() const {
    std::vector<double> out;
    out.reserve(samples.size());
    for (const Sample& s : samples) {
      double value;
      if (preop.sample(s.base_mm + lattice.value(s.cell), &value, nullptr))
        out.push_back(std::abs(s.intensity - (s.bias * value + offset)));
    }
    return out;
  }
};

// Membrane (graph Laplacian on the lattice's 6-neighbours) times alpha plus
// beta times the identity: the regulariser's Hessian.
void apply_prior(const Lattice& l, double alpha, double beta, const std::vector<Vec3>& x, std::vector<Vec3>* out) {
  out->assign(x.size(), Vec3::Zero());
  for (int c = 0; c < l.dim(2); ++c)
    for (int b = 0; b < l.dim(1); ++b)
      for (int a = 0; a < l.dim(0); ++a) {
        const int n = l.node(a, b, c);
        Vec3 y = beta * x[n];
        const int nb[6][3] = {{a - 1, b, c}, {a + 1, b, c}, {a, b - 1, c}, {a, b + 1, c}, {a, b, c - 1}, {a, b, c + 1}};
        for (const auto& m : nb)
          if (m[0] >= 0 && m[1] >= 0 && m[2] >= 0 && m[0] < l.dim(0) && m[1] < l.dim(1) && m[2] < l.dim(2))
            y += alpha * (x[n] - x[l.node(m[0], m[1], m[2])]);
        (*out)[n] = y;
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
  std::vector<Mat3> precond(n);
  for (std::size_t i = 0; i < n; ++i)
    precond[i] = (sys.hessian[i] + (6.0 * alpha + beta) * Mat3::Identity()).inverse();
  auto apply = [&](const std::vector<Vec3>& x, std::vector<Vec3>* y) {
    apply_prior(l, alpha, beta, x, y);
    for (std::size_t i = 0; i < n; ++i) (*y)[i] += sys.hessian[i] * x[i];
  };
  std::vector<Vec3> r = rhs;
  for (std::size_t i = 0; i < n; ++i) z[i] = precond[i] * r[i];
  p = z;
  double rz = dot(r, z);
  const double stop = 1e-8 * std::max(rz, 1e-300);
  for (int it = 0; it < 100 && rz > stop; ++it) {
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
  double max_mm = 0, sum_mm = 0;
  std::size_t voxels = 0;
};

// u += fade(x) v(x) over the lattice box; fade 1 inside the brain region,
// smoothly 0 at fade_mm outside it.
CorrectionStats apply_correction(VectorImage3& u, const Lattice& l, const ImageF& sdf_mm, const VoxelBox& box,
                                 double fade_mm) {
  CorrectionStats halves[2];
  const int slices = box.hi[2] - box.lo[2] + 1;
  parallel_halves(static_cast<std::size_t>(slices), 4, [&](std::size_t begin, std::size_t end) {
    CorrectionStats& st = halves[begin == 0 ? 0 : 1];
    for (std::size_t n = begin; n < end; ++n) {
      const int k = box.lo[2] + static_cast<int>(n);
      for (int j = box.lo[1]; j <= box.hi[1]; ++j)
        for (int i = box.lo[0]; i <= box.hi[0]; ++i) {
          const std::size_t v = u.grid.index(i, j, k);
          const double d = sdf_mm.voxels[v];
          const double m = d <= 0 ? 1.0 : fade_mm > 0 ? 1.0 - smoothstep(d / fade_mm) : 0.0;
          if (m <= 0) continue;
          const Vec3 c = m * l.value(l.locate(i, j, k));
          u.vectors[v] += c.cast<float>();
          if (d > 0) continue;
          st.max_mm = std::max(st.max_mm, c.norm());
          st.sum_mm += c.norm();
          ++st.voxels;
        }
    }
  });
  halves[0].max_mm = std::max(halves[0].max_mm, halves[1].max_mm);
  halves[0].sum_mm += halves[1].sum_mm;
  halves[0].voxels += halves[1].voxels;
  return halves[0];
}

void check_inputs(const VectorImage3& u, const IntensityRefinementInput& in) {
  const Grid3& g = u.grid;
  if (g.voxel_count() == 0 || u.vectors.size() != g.voxel_count())
    throw InputError("intensity refinement: the displacement field is empty");
  if (!in.intraop_t1.grid.same_geometry(g, 1e-3) || in.intraop_t1.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the intraop image is not on the field's grid");
  if (!in.intraop_labels.grid.same_geometry(g, 1e-3) || in.intraop_labels.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the intraop labels are not on the field's grid");
  if (!in.brain_sdf_mm.grid.same_geometry(g, 1e-3) || in.brain_sdf_mm.voxels.size() != g.voxel_count())
    throw InputError("intensity refinement: the brain distance map is not on the field's grid");
  if (in.preop_t1.grid.voxel_count() == 0 || in.preop_t1.voxels.size() != in.preop_t1.grid.voxel_count())
    throw InputError("intensity refinement: the preop image is empty");
}

double median_intensity(const std::vector<Sample>& s) {
  std::vector<double> v;
  v.reserve(s.size());
  for (const Sample& x : s) v.push_back(x.intensity);
  return robust_sigma(v) / 1.4826;  // the median of non-negative values
}

// The Gauss-Newton loop on the motion samples; returns the iterations done.
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
    // edges are closer to aligned.
    if (it == 0 || it == p.iterations / 2) {
      const BiasModel bias = fit_bias(bias_samples, lattice, preop, p.bias_degree, p.robust_scale);
      update_bias(motion, bias);
      data.offset = bias.offset;
      data.sigma = std::max(robust_sigma(data.abs_residuals()), sigma_floor);
      report->bias_model = describe(bias);
    }
    const NodeSystem sys = data.evaluate();
    if (it == 0) report->rms_residual_before = std::sqrt(sys.sum_r2 / std::max<std::size_t>(1, sys.used));
    const double moved = take_step(lattice, gauss_newton_step(sys, lattice, alpha, beta), p);
    if (moved < p.convergence_mm) {
      ++it;
      break;
    }
  }
  const NodeSystem last = data.evaluate();
  report->rms_residual_after = std::sqrt(last.sum_r2 / std::max<std::size_t>(1, last.used));
  return it;
}

}  // namespace

void validate(const IntensityRefinementParameters& p) {
  auto fail = [](const std::string& what) { throw InputError("intensity refinement: " + what); };
  if (!(p.lattice_spacing_mm >= 2 && p.lattice_spacing_mm <= 50)) fail("lattice_spacing_mm must be in [2, 50]");
  if (p.iterations < 1 || p.iterations > 100) fail("iterations must be in 1..100");
  if (!(p.convergence_mm > 0)) fail("convergence_mm must be > 0");
  if (!(p.membrane_weight >= 0) || !std::isfinite(p.membrane_weight)) fail("membrane_weight must be >= 0");
  if (!(p.shrink_weight_per_mm2 > 0) || !std::isfinite(p.shrink_weight_per_mm2))
    fail("shrink_weight_per_mm2 must be > 0 (without it a region without image edges is undetermined)");
  if (!(p.max_correction_mm > 0 && p.max_correction_mm <= 20)) fail("max_correction_mm must be in (0, 20]");
  if (!(p.max_step_mm > 0)) fail("max_step_mm must be > 0");
  if (!(p.sample_spacing_mm > 0)) fail("sample_spacing_mm must be > 0");
  if (p.max_samples < 1000) fail("max_samples must be >= 1000");
  if (!(p.boundary_margin_mm >= 0)) fail("boundary_margin_mm must be >= 0");
  if (!(p.robust_scale > 0)) fail("robust_scale must be > 0");
  if (p.bias_degree < 0 || p.bias_degree > 3) fail("bias_degree must be in 0..3");
  if (!(p.outside_fade_mm >= 0)) fail("outside_fade_mm must be >= 0");
}

void to_json(nlohmann::json& j, const IntensityRefinementReport& r) {
  if (!r.applied) {
    j = {{"applied", false}, {"skipped", r.skipped_reason}};
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
       {"seconds", r.seconds}};
}

IntensityRefinementReport refine_with_intensity(VectorImage3& pullback_mm, const IntensityRefinementInput& input,
                                                const IntensityRefinementParameters& p) {
  Stopwatch clock;
  validate(p);
  check_inputs(pullback_mm, input);
  IntensityRefinementReport report;
  const Grid3& grid = pullback_mm.grid;
  const VoxelBox box = region_box(input.brain_sdf_mm, p.outside_fade_mm);
  if (box.empty) {
    report.skipped_reason = "no brain region in the intraop labels";
    return report;
  }
  Lattice lattice(box, grid, p.lattice_spacing_mm);
  const LinearSampler preop(input.preop_t1);
  const InternalForeignDistance foreign(input.intraop_labels, input.brain_sdf_mm, input.background_label,
                                        p.boundary_margin_mm);
  SamplingContext ctx{pullback_mm, input, p, lattice, preop, foreign, std::vector<std::uint8_t>(65536, 0), {}, box};
  for (auto l : input.tissue_labels) ctx.tissue[l] = 1;
  const Vec3 voxel_mm = grid.spacing_mm();
  for (int a = 0; a < 3; ++a) ctx.stride[a] = std::max(1, static_cast<int>(std::lround(p.sample_spacing_mm / voxel_mm[a])));

  std::vector<Sample> candidates = collect_candidates(ctx);
  report.candidates = candidates.size();
  const double voxel_volume_mm3 = std::abs(grid.world_from_voxel.topLeftCorner<3, 3>().determinant());
  const double tissue_mm3 = static_cast<double>(candidates.size()) * ctx.stride[0] * ctx.stride[1] * ctx.stride[2] *
                            voxel_volume_mm3;
  std::vector<Sample> motion, bias_samples;
  select_samples(std::move(candidates), p.max_samples, &motion, &bias_samples);
  report.samples = motion.size();
  report.bias_samples = bias_samples.size();
  if (motion.size() < 1000) {
    report.skipped_reason = "too few tissue samples away from the boundary (" + std::to_string(motion.size()) + ")";
    return report;
  }
  const double median = std::max(median_intensity(bias_samples), 1e-12);
  const double density = static_cast<double>(motion.size()) / tissue_mm3;
  report.iterations = optimise(lattice, motion, bias_samples, preop, p, density, 1e-3 * median, &report);
  report.rms_residual_before /= median;
  report.rms_residual_after /= median;
  const CorrectionStats st = apply_correction(pullback_mm, lattice, input.brain_sdf_mm, box, p.outside_fade_mm);
  report.applied = true;
  report.max_correction_mm = st.max_mm;
  report.mean_correction_mm = st.voxels ? st.sum_mm / static_cast<double>(st.voxels) : 0.0;
  report.seconds = clock.seconds();
  return report;
}

}  // namespace brainshift
