#include "segmentation/tissue_em.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

#include "core/errors.h"
#include "core/parallel.h"
#include "segmentation/bias_field.h"
#include "segmentation/potts.h"

namespace brainshift::segmentation {

const GaussianClass* heaviest_class(const std::vector<GaussianClass>& classes, Tissue t) {
  const GaussianClass* best = nullptr;
  for (const auto& c : classes)
    if (c.tissue == t && (!best || c.weight > best->weight)) best = &c;
  return best;
}

namespace {

constexpr double kLogTiny = -1e30;

struct Samples {
  std::vector<std::array<int, 3>> voxel;
  std::vector<double> intensity;                 // normalised
  std::vector<std::array<double, kTissues>> log_prior;
  std::vector<char> band;  // in_surface_band
  std::vector<double> inside;  // prior of brain (parenchyma + ventricles), for the bias step
};

// Responsibilities of every sample for every class, one row of `classes`
// values per sample, contiguous: the E-step, M-step and bias step sweep it
// in order.
class Responsibilities {
 public:
  Responsibilities(std::size_t samples, std::size_t classes) : classes_(classes), gamma_(samples * classes, 0.0) {}
  double* row(std::size_t n) { return gamma_.data() + n * classes_; }
  const double* row(std::size_t n) const { return gamma_.data() + n * classes_; }
  std::size_t classes() const { return classes_; }

 private:
  std::size_t classes_;
  std::vector<double> gamma_;
};

double brain_prior_at(const TissuePrior& prior, std::size_t v) {
  return static_cast<double>(prior.p[index_of(Tissue::parenchyma)][v]) + prior.p[index_of(Tissue::ventricle)][v];
}

// Lattice points along an axis of n voxels at this stride, started half a
// stride in.
std::size_t lattice_points(int n, int stride) { return n > stride / 2 ? (n - stride / 2 - 1) / stride + 1 : 0; }

// A regular subsample of at most `budget` voxels: a lattice of about the same
// spacing in mm along every axis (strides per axis from the voxel spacing),
// started half a stride in. Rounding the strides alone could take up to 3x
// the budget (a stride of 1.49 voxels rounds to 1) and the fit's time with
// it: the finest axis in mm is coarsened until the lattice fits, at most
// every axis's voxels (a bounded loop). A stride through the voxels in grid
// order aliases whenever it shares a factor with a row's length (a stride of
// 55 on rows of 220 voxels sees 4 sagittal planes and nothing between them).
std::array<int, 3> sample_strides(const Grid3& g, std::size_t budget) {
  const Eigen::Vector3d spacing = g.spacing_mm();
  const double volume_mm3 = static_cast<double>(g.voxel_count()) * spacing.prod();
  const double h_mm = std::cbrt(volume_mm3 / static_cast<double>(std::max<std::size_t>(budget, 1)));
  std::array<int, 3> stride{};
  for (int a = 0; a < 3; ++a) stride[a] = std::max(1, static_cast<int>(std::lround(h_mm / spacing[a])));
  const auto count = [&] {
    return lattice_points(g.dims[0], stride[0]) * lattice_points(g.dims[1], stride[1]) *
           lattice_points(g.dims[2], stride[2]);
  };
  while (count() > budget) {
    int finest = -1;
    for (int a = 0; a < 3; ++a)
      if (stride[a] < g.dims[a] && (finest < 0 || stride[a] * spacing[a] < stride[finest] * spacing[finest])) finest = a;
    if (finest < 0) break;
    stride[finest] += 1;
  }
  return stride;
}

Samples draw_samples(const ImageF& image, const TissuePrior& prior, double scale, std::size_t budget) {
  const auto& g = image.grid;
  const std::array<int, 3> stride = sample_strides(g, budget);
  Samples s;
  for (int k = stride[2] / 2; k < g.dims[2]; k += stride[2])
    for (int j = stride[1] / 2; j < g.dims[1]; j += stride[1])
      for (int i = stride[0] / 2; i < g.dims[0]; i += stride[0]) {
        const std::size_t v = g.index(i, j, k);
        s.voxel.push_back({i, j, k});
        s.intensity.push_back(image.voxels[v] / scale);
        std::array<double, kTissues> lp{};
        for (int t = 0; t < kTissues; ++t) lp[t] = prior.p[t][v] > 0 ? std::log(prior.p[t][v]) : kLogTiny;
        s.log_prior.push_back(lp);
        s.band.push_back(in_surface_band(brain_prior_at(prior, v)));
        s.inside.push_back(std::exp(lp[0]) + std::exp(lp[1]));
      }
  return s;
}

// Intensity scale: the 99th percentile inside the prior's brain, so the
// numbers the fit works with are of order 1 for any scanner's units.
double brain_intensity_scale(const ImageF& image, const TissuePrior& prior) {
  std::vector<float> inside;
  for (std::size_t v = 0; v < image.voxels.size(); ++v)
    if (prior.p[0][v] + prior.p[1][v] > 0.5f) inside.push_back(image.voxels[v]);
  if (inside.empty()) throw InputError("segmentation: the prior places no brain in the image");
  const std::size_t at = static_cast<std::size_t>(0.99 * (inside.size() - 1));
  std::nth_element(inside.begin(), inside.begin() + static_cast<std::ptrdiff_t>(at), inside.end());
  const double scale = inside[at];
  if (!(scale > 0)) throw InputError("segmentation: the image is empty or not positive inside the brain");
  return scale;
}

// Weighted quantile of sorted (value, weight) pairs.
double quantile(const std::vector<std::pair<double, double>>& sorted, double total, double q) {
  double acc = 0;
  for (const auto& [v, w] : sorted) {
    acc += w;
    if (acc >= q * total) return v;
  }
  return sorted.back().first;
}

// The intensities the prior is sure of for tissue t ("sure" relative to the
// most the prior says of it anywhere: a small structure never reaches 0.9),
// as (intensity, weight) pairs.
std::vector<std::pair<double, double>> sure_intensities(const Samples& s, const std::vector<double>& intensity, int t) {
  std::vector<std::pair<double, double>> vw;
  double top = 0;
  for (const auto& lp : s.log_prior) top = std::max(top, std::exp(lp[t]));
  for (double sure : {0.9 * top, 0.5 * top, 0.0}) {
    vw.clear();
    for (std::size_t n = 0; n < s.intensity.size(); ++n) {
      const double w = std::exp(s.log_prior[n][t]);
      if (w >= sure) vw.emplace_back(intensity[n], sure > 0 ? w : 1.0);
    }
    if (vw.size() >= 50) break;
  }
  return vw;
}

// The ventricles' fluid, found without trusting where their prior is sure:
// brain shift moves them by several mm (docs/DESIGN.md "Automatic intraop
// segmentation"), farther than their bodies are thick, so where the carried
// ventricles were the image may show white matter. Their neighbourhood (the
// ventricles' prior at least a quarter: where they may have gone) holds
// them, deep grey and white matter. In every MR contrast that shows the
// ventricles at all their fluid lies at one end of these intensities (darkest
// in T1 and FLAIR, brightest in T2; grey matter lies between), and stands
// apart from the bulk of the tissue: of the two tails holding as many samples
// as the ventricles' volume, the fluid's is the one farther from the
// neighbourhood's median. Returns {median, sd} of that tail; {0, 0} when there
// are too few samples.
std::pair<double, double> fluid_class(const Samples& s, const std::vector<double>& intensity, double share) {
  constexpr double kNeighbourhood = 0.25;
  const int vent = index_of(Tissue::ventricle), par = index_of(Tissue::parenchyma);
  std::vector<std::pair<double, double>> near;  // intensity, weight 1
  std::size_t brain = 0;
  for (std::size_t n = 0; n < s.intensity.size(); ++n) {
    const double p_vent = std::exp(s.log_prior[n][vent]);
    brain += std::exp(s.log_prior[n][par]) + p_vent >= 0.5;
    if (p_vent >= kNeighbourhood) near.emplace_back(intensity[n], 1.0);
  }
  const auto tail = std::min(static_cast<std::size_t>(std::max(share, 0.0) * static_cast<double>(brain)), near.size() / 2);
  if (tail < 20) return {0, 0};
  std::sort(near.begin(), near.end());
  const double median = near[near.size() / 2].first;
  const std::vector<std::pair<double, double>> low(near.begin(), near.begin() + static_cast<std::ptrdiff_t>(tail));
  const std::vector<std::pair<double, double>> high(near.end() - static_cast<std::ptrdiff_t>(tail), near.end());
  const double t = static_cast<double>(tail);
  const bool dark = median - quantile(low, t, 0.5) >= quantile(high, t, 0.5) - median;
  const auto& fluid = dark ? low : high;
  const double sd = (quantile(fluid, t, 0.75) - quantile(fluid, t, 0.25)) / 1.349;
  return {quantile(fluid, t, 0.5), std::max(sd, 0.01)};
}

// Each tissue's classes start from its intensities (no ordering of tissues is
// assumed): one class at their median, several spread evenly over their
// 2-98 % range, so that a rare bright tissue (fat, a T2's fluid) gets a class
// even where a dark one (air) fills most voxels. The ventricles start from
// the brain's fluid (fluid_class), the other tissues, large enough that a shift leaves most of them in place,
// from where their prior is sure.
std::vector<GaussianClass> initial_classes(const Samples& s, const std::vector<double>& intensity,
                                           const std::array<int, kTissues>& classes_per_tissue,
                                           double ventricle_share) {
  std::vector<GaussianClass> classes;
  const auto [fluid_mean, fluid_sd] = fluid_class(s, intensity, ventricle_share);
  for (int t = 0; t < kTissues; ++t) {
    const int K = classes_per_tissue[t];
    if (t == index_of(Tissue::ventricle) && K == 1 && fluid_sd > 0) {
      classes.push_back({Tissue::ventricle, fluid_mean, fluid_sd, 1.0});
      continue;
    }
    std::vector<std::pair<double, double>> vw = sure_intensities(s, intensity, t);
    std::sort(vw.begin(), vw.end());
    double total = 0;
    for (const auto& p : vw) total += p.second;
    const double lo = quantile(vw, total, 0.02), hi = quantile(vw, total, 0.98);
    const double median = quantile(vw, total, 0.5);
    for (int c = 0; c < K; ++c) {
      GaussianClass g;
      g.tissue = static_cast<Tissue>(t);
      if (K == 1) {
        g.mean = median;
        g.sd = std::max(1.4826 * (quantile(vw, total, 0.75) - quantile(vw, total, 0.25)) / 1.349, 0.01);
      } else {
        g.mean = lo + (c + 0.5) / K * (hi - lo);
        g.sd = std::max((hi - lo) / (2.0 * K), 0.01);
      }
      g.weight = 1.0 / K;
      classes.push_back(g);
    }
    // The fluid around the brain (subarachnoid, under the craniotomy, in a
    // cavity) is the ventricles' fluid: the outside's class nearest to it
    // starts there, so that no parenchyma class has to take it.
    if (t == index_of(Tissue::outside) && K > 1 && fluid_sd > 0) {
      auto nearest = classes.end() - K;
      for (auto c = classes.end() - K; c != classes.end(); ++c)
        if (std::abs(c->mean - fluid_mean) < std::abs(nearest->mean - fluid_mean)) nearest = c;
      nearest->mean = fluid_mean;
      nearest->sd = fluid_sd;
      // And one more outside class, the fluid around the brain held to the
      // ventricles' fluid (hold_surface_fluid): without a share (weight 0,
      // no part in the fit) until the fit finds the fluid the brightest
      // tissue.
      GaussianClass held{Tissue::outside, fluid_mean, fluid_sd, 0.0};
      held.surface_fluid = true;
      classes.push_back(held);
    }
  }
  return classes;
}

// What the likelihood needs of each class, taken once per EM iteration
// rather than per sample and class: the logarithms dominated the fit's time.
struct ClassTerms {
  std::vector<int> tissue;
  std::vector<double> mean, inv_sd;
  std::array<std::vector<double>, 2> log_scale;  // log(share / sd): [0] elsewhere, [1] in the surface band
};

double band_share(const GaussianClass& g) { return g.band_weight > 0 ? g.band_weight : g.weight; }

ClassTerms class_terms(const std::vector<GaussianClass>& classes) {
  ClassTerms k;
  for (const auto& g : classes) {
    k.tissue.push_back(index_of(g.tissue));
    k.mean.push_back(g.mean);
    k.inv_sd.push_back(1.0 / g.sd);
    k.log_scale[0].push_back(std::log(g.weight) - std::log(g.sd));
    k.log_scale[1].push_back(std::log(band_share(g)) - std::log(g.sd));
  }
  return k;
}

// log sum_c pi_c N(x; mu_c, sd_c) + log prior_t per tissue, and the class
// responsibilities; returns log sum over everything.
double responsibilities(double x, const std::array<double, kTissues>& log_prior, const ClassTerms& k, bool band,
                        double* gamma) {
  const std::size_t C = k.mean.size();
  double top = -std::numeric_limits<double>::infinity();
  const std::vector<double>& log_scale = k.log_scale[band ? 1 : 0];
  for (std::size_t c = 0; c < C; ++c) {
    const double z = (x - k.mean[c]) * k.inv_sd[c];
    gamma[c] = log_prior[k.tissue[c]] + log_scale[c] - 0.5 * z * z;
    top = std::max(top, gamma[c]);
  }
  double sum = 0;
  for (std::size_t c = 0; c < C; ++c) sum += (gamma[c] = std::exp(gamma[c] - top));
  for (std::size_t c = 0; c < C; ++c) gamma[c] /= sum;
  return top + std::log(sum);
}

// Smallest class spread, relative to the brain's 99th percentile: well below
// any tissue's noise at the lowest SNR an intraop scanner gives (about 1/25),
// only keeps a class from collapsing onto a few identical voxels.
constexpr double kMinSd = 0.005;

// The fluid around the brain in a bright-fluid (T2-like) image. There a
// parenchyma class can span the partial volume of the bright fluid rim
// around the brain, where the prior still leans to brain, while the
// outside's fluid, a small share of an outside made mostly of air, bone and
// scalp, loses it (docs/PERFORMANCE.md 12.11). The rim is CSF, the same
// fluid as in the ventricles: an outside class of its own (surface_fluid) is
// held to the ventricles' fitted class (mean and sd: it cannot drift to
// another tissue), and next to the outline (in_surface_band), where the
// outside is that fluid and the dura rather than air, bone and scalp, it has
// a share of its own, at least its share of the whole outside; the other
// outside classes, which stay free (bright fat and scalp need a class of
// their own), keep their proportions of the rest there (a share of their own
// let scalp-like classes take grey matter, 12.14). Not in a dark-fluid
// (T1-like) image: there the outside's dark classes take the dark rim
// already, and a band share for the dark fluid took the cortex (12.14); the
// held class keeps a share of 0 and takes no part, so those images are
// classified exactly as before.
void hold_surface_fluid(const std::vector<double>& w, const std::vector<double>& w_band,
                        std::vector<GaussianClass>& classes) {
  const auto held = std::find_if(classes.begin(), classes.end(), [](const GaussianClass& g) { return g.surface_fluid; });
  if (held == classes.end()) return;
  const GaussianClass* ventricle = heaviest_class(classes, Tissue::ventricle);
  double brightest_tissue = -std::numeric_limits<double>::infinity();
  for (const auto& g : classes)
    if (g.tissue == Tissue::parenchyma) brightest_tissue = std::max(brightest_tissue, g.mean);
  const auto f = static_cast<std::size_t>(held - classes.begin());
  const bool bright_fluid = ventricle && ventricle->mean > brightest_tissue;
  for (auto& g : classes) g.band_weight = 0;
  if (!bright_fluid && held->weight == 0) return;  // never entered: the fit as without it
  // The held class's share of the whole outside: from its responsibilities
  // (maximise), or, when it enters, the even start every outside class had
  // (1 / their number); 0 when the fluid is no longer the brightest tissue.
  // In the band, its share there, at least that. The others share the rest
  // in their fitted proportions, in the band as elsewhere.
  int outside_classes = 0;
  double others = 0, outside_band = 0;
  for (std::size_t c = 0; c < classes.size(); ++c)
    if (classes[c].tissue == Tissue::outside) {
      outside_classes += 1;
      outside_band += w_band[c];
      if (c != f) others += classes[c].weight;
    }
  double share = 0, band_share = 0;
  if (bright_fluid) {
    share = std::clamp(w[f] > 1e-9 ? held->weight : 1.0 / outside_classes, 1e-6, 1 - 1e-6);
    band_share = w[f] > 1e-9 && outside_band > 0 ? w_band[f] / outside_band : share;
    band_share = std::clamp(band_share, share, 1 - 1e-6);
    held->mean = ventricle->mean;
    held->sd = ventricle->sd;
  }
  for (std::size_t c = 0; c < classes.size(); ++c) {
    GaussianClass& g = classes[c];
    if (g.tissue != Tissue::outside || c == f || !(others > 0)) continue;
    const double proportion = g.weight / others;
    g.weight = std::max(proportion * (1 - share), 1e-6);
    if (bright_fluid) g.band_weight = std::max(proportion * (1 - band_share), 1e-6);
  }
  held->weight = share;
  held->band_weight = band_share;
}

void maximise(const Samples& s, const Responsibilities& gamma, const std::vector<double>& corrected,
              std::vector<GaussianClass>& classes, bool fixed_ventricle_class) {
  const std::size_t C = classes.size();
  std::vector<double> w(C, 0), m(C, 0), q(C, 0), w_band(C, 0);
  for (std::size_t n = 0; n < s.intensity.size(); ++n) {
    const double* g = gamma.row(n);
    for (std::size_t c = 0; c < C; ++c) {
      w[c] += g[c];
      m[c] += g[c] * corrected[n];
      if (s.band[n]) w_band[c] += g[c];
    }
  }
  for (std::size_t c = 0; c < C; ++c) m[c] = w[c] > 0 ? m[c] / w[c] : classes[c].mean;
  for (std::size_t n = 0; n < s.intensity.size(); ++n) {
    const double* g = gamma.row(n);
    for (std::size_t c = 0; c < C; ++c) q[c] += g[c] * (corrected[n] - m[c]) * (corrected[n] - m[c]);
  }
  std::array<double, kTissues> tissue_weight{};
  for (std::size_t c = 0; c < C; ++c) tissue_weight[index_of(classes[c].tissue)] += w[c];
  for (std::size_t c = 0; c < C; ++c) {
    if (w[c] <= 1e-9) continue;  // an empty class keeps its parameters
    if (fixed_ventricle_class && classes[c].tissue == Tissue::ventricle) continue;
    classes[c].mean = m[c];
    classes[c].sd = std::max(std::sqrt(q[c] / w[c]), kMinSd);
    classes[c].weight = std::max(w[c] / tissue_weight[index_of(classes[c].tissue)], 1e-6);
  }
  hold_surface_fluid(w, w_band, classes);
}

// The bias step: per sample the log of image / its class's mean, weighted by
// that ratio's precision (mu^2 / sd^2), over brain samples whose class is
// clear (responsibility >= 0.9). Partial-volume voxels between two classes
// and the outside (air's ratio is noise; the scalp lies under other coils'
// fall-off) would only pull the fit away from the tissue that matters.
// Only the brain's core informs the bias: where the prior is this sure of
// brain (about 4.6 prior widths inside the carried outline) there is no
// partial volume with the fluid and dura around the brain, whose mixed
// intensities would otherwise be read as a darkening of the periphery.
constexpr double kBiasCoreInside = 0.99;

constexpr double kBiasInlierSd = 2.5;
const double kMaxLogBias = std::log(4.0);

void fit_bias(const Samples& s, const Responsibilities& gamma, const std::vector<double>& corrected,
              const std::vector<GaussianClass>& classes, LogBiasField& bias) {
  std::vector<double> ratio(s.intensity.size(), 0), weight(s.intensity.size(), 0);
  for (std::size_t n = 0; n < s.intensity.size(); ++n) {
    const double* row = gamma.row(n);
    const auto best = static_cast<std::size_t>(std::max_element(row, row + gamma.classes()) - row);
    const GaussianClass& g = classes[best];
    if (s.inside[n] < kBiasCoreInside || row[best] < 0.9 || g.tissue == Tissue::outside || s.intensity[n] <= 0 ||
        g.mean <= 0)
      continue;
    // A tissue no class describes (a tumour, blood) is not a bias.
    if (std::abs(corrected[n] - g.mean) > kBiasInlierSd * g.sd) continue;
    ratio[n] = std::log(s.intensity[n] / g.mean);
    weight[n] = g.mean * g.mean / (g.sd * g.sd);
  }
  // Enough samples to determine the polynomial many times over, and a
  // field within what coils do (a few-fold across a head even with surface
  // coils); otherwise the previous field stands.
  const auto used = static_cast<std::size_t>(std::count_if(weight.begin(), weight.end(), [](double w) { return w > 0; }));
  if (used < 20 * bias.terms()) return;
  LogBiasField next = bias;
  if (!next.fit(s.voxel, ratio, weight)) return;
  for (std::size_t n = 0; n < s.intensity.size(); ++n)
    if (weight[n] > 0 && std::abs(next.log_bias(s.voxel[n][0], s.voxel[n][1], s.voxel[n][2])) > kMaxLogBias) return;
  bias = next;
}

// log b at every sample (each on its own: both cores, the same result).
// The samples' log bias and the intensities it corrects, taken again only
// when the bias moves.
void refresh_log_bias(const Samples& s, const LogBiasField& bias, std::vector<double>& log_b,
                      std::vector<double>& corrected) {
  parallel_halves(log_b.size(), 8192, [&](std::size_t begin, std::size_t end) {
    for (std::size_t n = begin; n < end; ++n) {
      log_b[n] = bias.log_bias(s.voxel[n][0], s.voxel[n][1], s.voxel[n][2]);
      corrected[n] = s.intensity[n] * std::exp(-log_b[n]);
    }
  });
}

// Every voxel: tissue evidence prior_t * sum_c pi_c N(x) (x the intensity
// over `scale` and the bias; classes in those units), then the Potts
// smoothing: out.posterior and out.bias.
void classify_voxels(const ImageF& image, const TissuePrior& prior, double scale,
                     const std::vector<GaussianClass>& classes, const std::vector<float>& log_bias,
                     const EmParameters& params, EmResult& out) {
  const std::size_t V = image.grid.voxel_count();
  std::array<std::vector<float>, kTissues> evidence;
  for (auto& e : evidence) e.resize(V);
  out.bias.resize(V);
  // In the linear domain, scaled by the largest class term: one exp per
  // class and voxel, no logarithm (a voxel far from every class still has
  // its nearest class's term at 1, so the sum never vanishes).
  const ClassTerms terms = class_terms(classes);
  // Each voxel on its own: the two halves side by side, the same result.
  parallel_halves(V, 1 << 16, [&](std::size_t begin, std::size_t end) {
    std::vector<double> l(classes.size());
    for (std::size_t v = begin; v < end; ++v) {
      out.bias[v] = std::exp(log_bias[v]);
      const double x = image.voxels[v] / scale / out.bias[v];
      double m = -std::numeric_limits<double>::infinity();
      const std::vector<double>& log_scale = terms.log_scale[in_surface_band(brain_prior_at(prior, v)) ? 1 : 0];
      for (std::size_t c = 0; c < l.size(); ++c) {
        const double z = (x - terms.mean[c]) * terms.inv_sd[c];
        l[c] = log_scale[c] - 0.5 * z * z;
        m = std::max(m, l[c]);
      }
      std::array<double, kTissues> e{};
      for (std::size_t c = 0; c < l.size(); ++c) e[terms.tissue[c]] += std::exp(l[c] - m);
      double top = 0;
      for (int t = 0; t < kTissues; ++t) top = std::max(top, e[t] *= std::max<double>(prior.p[t][v], 1e-30));
      for (int t = 0; t < kTissues; ++t) evidence[t][v] = static_cast<float>(e[t] / top);
    }
  });
  out.posterior = potts_mean_field(evidence, image.grid, params.mrf_beta, params.mrf_sweeps);
}

}  // namespace

bool fluid_is_bright(const std::vector<GaussianClass>& classes) {
  const GaussianClass* fluid = heaviest_class(classes, Tissue::ventricle);
  const GaussianClass* bulk = heaviest_class(classes, Tissue::parenchyma);
  return fluid && bulk && fluid->mean > bulk->mean;
}

EmResult classify_with_classes(const ImageF& image, const TissuePrior& prior, const std::vector<GaussianClass>& classes,
                               const std::vector<float>& log_bias, const EmParameters& params) {
  if (!image.grid.same_geometry(prior.grid)) throw InputError("segmentation: image and prior on different grids");
  if (log_bias.size() != image.grid.voxel_count()) throw InputError("segmentation: the bias does not fit the image");
  if (classes.empty()) throw InputError("segmentation: no classes to classify with");
  for (const auto& g : classes)
    if (!(g.sd > 0) || !(g.weight > 0 || (g.surface_fluid && g.weight == 0)))
      throw InputError("segmentation: a class without spread or weight");
  EmResult out;
  classify_voxels(image, prior, 1.0, classes, log_bias, params, out);
  out.classes = classes;
  out.converged = true;
  return out;
}

namespace {

EmResult fit_mixture_once(const ImageF& image, const TissuePrior& prior, const EmParameters& params) {
  if (!image.grid.same_geometry(prior.grid)) throw InputError("segmentation: image and prior on different grids");
  for (int K : params.classes)
    if (K < 1 || K > 6) throw InputError("segmentation: 1 to 6 classes per tissue");
  const double scale = brain_intensity_scale(image, prior);
  const Samples s = draw_samples(image, prior, scale, params.fit_samples);
  const std::size_t N = s.intensity.size();
  EmResult out;
  out.samples = N;
  // corrected: the intensities the last E-step saw (the next phase's classes
  // start from them); bias_corrected: under the bias as it now stands.
  std::vector<double> corrected = s.intensity, bias_corrected = s.intensity, log_b(N, 0);
  // Two phases. First a bias of degree 1 at most: a linear field cannot
  // mimic the grey rind around a brighter white core (a quadratic can: the
  // classic local optimum of EM with a bias, where the field takes the
  // periphery's grey matter and the classes split white matter by region).
  // Then the full degree, with the classes started again from the corrected
  // intensities.
  std::vector<GaussianClass> classes;
  LogBiasField bias(image.grid, std::min(params.bias_degree, 1));
  for (int phase = 0; phase < 2; ++phase) {
    if (phase == 1) {
      LogBiasField full(image.grid, params.bias_degree);
      full.start_from(bias);
      bias = full;
    }
    classes = initial_classes(s, corrected, params.classes, prior.ventricle_share);
    const int budget = phase == 0 ? std::min(params.max_iterations, 10) : params.max_iterations;
    Responsibilities gamma(N, classes.size());
    double previous = -std::numeric_limits<double>::infinity();
    // The bias step fits on the samples whose class is clear, so it need not
    // raise the likelihood as an EM step does: a step that lowers it is
    // undone and the bias kept as it was from then on.
    LogBiasField before_bias = bias;
    bool bias_moved = false, bias_frozen = params.bias_degree == 0;
    for (int it = 0; it < budget; ++it) {
      const ClassTerms terms = class_terms(classes);
      // The two halves of the samples side by side, always summed as two
      // partial sums: the same likelihood on one core or two.
      std::array<double, 2> partial{0, 0};
      on_two_halves(N, [&](std::size_t begin, std::size_t end, std::size_t half) {
        // Summed here and stored once: both halves' partial sums share a
        // cache line, and adding into it per sample made the E-step half as
        // fast on two cores (the same sums in the same order).
        double sum = 0;
        for (std::size_t n = begin; n < end; ++n) {
          corrected[n] = bias_corrected[n];
          sum += responsibilities(corrected[n], s.log_prior[n], terms, s.band[n], gamma.row(n)) - log_b[n];
        }
        partial[half] = sum;
      });
      const double ll = (partial[0] + partial[1]) / static_cast<double>(N);
      out.iterations += 1;
      if (bias_moved && ll < previous) {
        bias = before_bias;
        bias_frozen = true;
        bias_moved = false;
        refresh_log_bias(s, bias, log_b, bias_corrected);
        continue;
      }
      out.mean_log_likelihood = ll;
      out.converged = std::abs(ll - previous) < params.tolerance;
      if (out.converged) break;
      previous = ll;
      maximise(s, gamma, corrected, classes, params.fixed_ventricle_class);
      bias_moved = false;
      if (!bias_frozen) {
        before_bias = bias;
        fit_bias(s, gamma, corrected, classes, bias);
        bias_moved = true;
        refresh_log_bias(s, bias, log_b, bias_corrected);
      }
    }
  }

  classify_voxels(image, prior, scale, classes, bias.log_bias_image(), params, out);
  out.bias_field = bias;
  for (auto& g : classes) {
    g.mean *= scale;
    g.sd *= scale;
  }
  out.classes = std::move(classes);
  return out;
}

}  // namespace

// On an image whose fluid is dark, a parenchyma class within the spread of
// the brain's fluid (less than one of the fluid class's sd above its mean,
// or below it) is that fluid taken for tissue (sulcal CSF, the fluid of a
// gap under a sunken cortex), not a tissue: no parenchyma is as dark as CSF
// on a T1 or a FLAIR (oedema is not; on a T2 it is as bright as the fluid,
// and bright-fluid images are left alone). It happens where grey and white matter lie close (a FLAIR-like
// image: 0.62 and 0.45 of white matter's T1 signal), and the class then
// holds the gap's fluid as brain (docs/PERFORMANCE.md 12.37).
static bool parenchyma_class_is_fluid(const std::vector<GaussianClass>& classes) {
  const GaussianClass* fluid = heaviest_class(classes, Tissue::ventricle);
  const GaussianClass* bulk = heaviest_class(classes, Tissue::parenchyma);
  // A bright-fluid (T2-like) image's oedema is tissue as bright as fluid.
  if (!fluid || !bulk || fluid_is_bright(classes)) return false;
  for (const auto& c : classes)
    if (c.tissue == Tissue::parenchyma && &c != bulk && c.mean - fluid->mean < fluid->sd) return true;
  return false;
}

EmResult fit_tissue_mixture(const ImageF& image, const TissuePrior& prior, const EmParameters& params) {
  EmResult out = fit_mixture_once(image, prior, params);
  // Fitted again with one parenchyma class fewer, at most until one is left.
  const int par = index_of(Tissue::parenchyma);
  EmParameters fewer = params;
  while (fewer.classes[par] > 1 && parenchyma_class_is_fluid(out.classes)) {
    fewer.classes[par] -= 1;
    const int iterations = out.iterations;
    out = fit_mixture_once(image, prior, fewer);
    out.iterations += iterations;
    out.parenchyma_classes_dropped += params.classes[par] - fewer.classes[par];
  }
  return out;
}

}  // namespace brainshift::segmentation
