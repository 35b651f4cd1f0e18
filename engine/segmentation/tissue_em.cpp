#include "segmentation/tissue_em.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

#include "core/errors.h"
#include "segmentation/bias_field.h"
#include "segmentation/potts.h"

namespace brainshift::segmentation {
namespace {

constexpr double kLogTiny = -1e30;

struct Samples {
  std::vector<std::array<int, 3>> voxel;
  std::vector<double> intensity;                 // normalised
  std::vector<std::array<double, kTissues>> log_prior;
};

// A regular subsample of about `budget` voxels: every step-th voxel in grid
// order, the step odd so that it does not alias with a row length.
Samples draw_samples(const ImageF& image, const TissuePrior& prior, double scale, std::size_t budget) {
  const auto& g = image.grid;
  std::size_t step = std::max<std::size_t>(1, g.voxel_count() / std::max<std::size_t>(budget, 1));
  if (step > 1 && step % 2 == 0) ++step;
  Samples s;
  for (std::size_t v = 0; v < g.voxel_count(); v += step) {
    const int i = static_cast<int>(v % g.dims[0]);
    const int j = static_cast<int>((v / g.dims[0]) % g.dims[1]);
    const int k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    s.voxel.push_back({i, j, k});
    s.intensity.push_back(image.voxels[v] / scale);
    std::array<double, kTissues> lp{};
    for (int t = 0; t < kTissues; ++t) lp[t] = prior.p[t][v] > 0 ? std::log(prior.p[t][v]) : kLogTiny;
    s.log_prior.push_back(lp);
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

// Each tissue's classes start from the intensities the prior is sure of for
// it (no ordering of tissues is assumed): one class at their median, several
// spread evenly over their 2-98 % range, so that a rare bright tissue (fat,
// a T2's fluid) gets a class even where a dark one (air) fills most voxels.
std::vector<GaussianClass> initial_classes(const Samples& s, const std::vector<double>& intensity,
                                           const std::array<int, kTissues>& classes_per_tissue) {
  std::vector<GaussianClass> classes;
  for (int t = 0; t < kTissues; ++t) {
    std::vector<std::pair<double, double>> vw;  // intensity, prior weight
    for (double sure : {0.9, 0.5, 0.0}) {
      vw.clear();
      for (std::size_t n = 0; n < s.intensity.size(); ++n) {
        const double w = std::exp(s.log_prior[n][t]);
        if (w >= sure) vw.emplace_back(intensity[n], sure > 0 ? w : 1.0);
      }
      if (vw.size() >= 50) break;
    }
    std::sort(vw.begin(), vw.end());
    double total = 0;
    for (const auto& p : vw) total += p.second;
    const int K = classes_per_tissue[t];
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
  }
  return classes;
}

double log_gauss(double x, const GaussianClass& g) {
  const double z = (x - g.mean) / g.sd;
  return -std::log(g.sd) - 0.5 * z * z;
}

// log sum_c pi_c N(x; mu_c, sd_c) + log prior_t per tissue, and the class
// responsibilities; returns log sum over everything.
double responsibilities(double x, const std::array<double, kTissues>& log_prior,
                        const std::vector<GaussianClass>& classes, std::vector<double>& gamma) {
  double top = -std::numeric_limits<double>::infinity();
  for (std::size_t c = 0; c < classes.size(); ++c) {
    gamma[c] = log_prior[index_of(classes[c].tissue)] + std::log(classes[c].weight) + log_gauss(x, classes[c]);
    top = std::max(top, gamma[c]);
  }
  double sum = 0;
  for (double& g : gamma) sum += (g = std::exp(g - top));
  for (double& g : gamma) g /= sum;
  return top + std::log(sum);
}

// Smallest class spread, relative to the brain's 99th percentile: well below
// any tissue's noise at the lowest SNR an intraop scanner gives (about 1/25),
// only keeps a class from collapsing onto a few identical voxels.
constexpr double kMinSd = 0.005;

void maximise(const Samples& s, const std::vector<std::vector<double>>& gamma, const std::vector<double>& corrected,
              std::vector<GaussianClass>& classes) {
  const std::size_t C = classes.size();
  std::vector<double> w(C, 0), m(C, 0), q(C, 0);
  for (std::size_t n = 0; n < s.intensity.size(); ++n)
    for (std::size_t c = 0; c < C; ++c) {
      w[c] += gamma[n][c];
      m[c] += gamma[n][c] * corrected[n];
    }
  for (std::size_t c = 0; c < C; ++c) m[c] = w[c] > 0 ? m[c] / w[c] : classes[c].mean;
  for (std::size_t n = 0; n < s.intensity.size(); ++n)
    for (std::size_t c = 0; c < C; ++c) q[c] += gamma[n][c] * (corrected[n] - m[c]) * (corrected[n] - m[c]);
  std::array<double, kTissues> tissue_weight{};
  for (std::size_t c = 0; c < C; ++c) tissue_weight[index_of(classes[c].tissue)] += w[c];
  for (std::size_t c = 0; c < C; ++c) {
    if (w[c] <= 1e-9) continue;  // an empty class keeps its parameters
    classes[c].mean = m[c];
    classes[c].sd = std::max(std::sqrt(q[c] / w[c]), kMinSd);
    classes[c].weight = std::max(w[c] / tissue_weight[index_of(classes[c].tissue)], 1e-6);
  }
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

void fit_bias(const Samples& s, const std::vector<std::vector<double>>& gamma, const std::vector<GaussianClass>& classes,
              LogBiasField& bias) {
  std::vector<double> ratio(s.intensity.size(), 0), weight(s.intensity.size(), 0);
  for (std::size_t n = 0; n < s.intensity.size(); ++n) {
    const auto best = static_cast<std::size_t>(
        std::max_element(gamma[n].begin(), gamma[n].end()) - gamma[n].begin());
    const GaussianClass& g = classes[best];
    const double inside = std::exp(s.log_prior[n][0]) + std::exp(s.log_prior[n][1]);
    if (inside < kBiasCoreInside || gamma[n][best] < 0.9 || g.tissue == Tissue::outside || s.intensity[n] <= 0 ||
        g.mean <= 0)
      continue;
    ratio[n] = std::log(s.intensity[n] / g.mean);
    weight[n] = g.mean * g.mean / (g.sd * g.sd);
  }
  bias.fit(s.voxel, ratio, weight);
}

}  // namespace

EmResult fit_tissue_mixture(const ImageF& image, const TissuePrior& prior, const EmParameters& params) {
  if (!image.grid.same_geometry(prior.grid)) throw InputError("segmentation: image and prior on different grids");
  for (int K : params.classes)
    if (K < 1 || K > 6) throw InputError("segmentation: 1 to 6 classes per tissue");
  const double scale = brain_intensity_scale(image, prior);
  const Samples s = draw_samples(image, prior, scale, params.fit_samples);
  const std::size_t N = s.intensity.size();
  std::vector<double> corrected = s.intensity, log_b(N, 0);
  EmResult out;
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
    classes = initial_classes(s, corrected, params.classes);
    const int budget = phase == 0 ? std::min(params.max_iterations, 10) : params.max_iterations;
    std::vector<std::vector<double>> gamma(N, std::vector<double>(classes.size(), 0));
    double previous = -std::numeric_limits<double>::infinity();
    for (int it = 0; it < budget; ++it) {
      double ll = 0;
      for (std::size_t n = 0; n < N; ++n) {
        corrected[n] = s.intensity[n] * std::exp(-log_b[n]);
        ll += responsibilities(corrected[n], s.log_prior[n], classes, gamma[n]) - log_b[n];
      }
      ll /= static_cast<double>(N);
      out.iterations += 1;
      out.mean_log_likelihood = ll;
      out.converged = std::abs(ll - previous) < params.tolerance;
      if (out.converged) break;
      previous = ll;
      maximise(s, gamma, corrected, classes);
      if (params.bias_degree > 0) {
        fit_bias(s, gamma, classes, bias);
        for (std::size_t n = 0; n < N; ++n) log_b[n] = bias.log_bias(s.voxel[n][0], s.voxel[n][1], s.voxel[n][2]);
      }
    }
  }

  // Every voxel: tissue evidence prior_t * sum_c pi_c N(x), scaled per voxel.
  const std::size_t V = image.grid.voxel_count();
  const std::vector<float> log_bias = bias.log_bias_image();
  std::array<std::vector<float>, kTissues> evidence;
  for (auto& e : evidence) e.resize(V);
  out.bias.resize(V);
  std::vector<double> lt(kTissues);
  for (std::size_t v = 0; v < V; ++v) {
    out.bias[v] = std::exp(log_bias[v]);
    const double x = image.voxels[v] / scale / out.bias[v];
    std::fill(lt.begin(), lt.end(), -std::numeric_limits<double>::infinity());
    for (const auto& g : classes) {
      const int t = index_of(g.tissue);
      const double l = std::log(std::max<double>(prior.p[t][v], 1e-30)) + std::log(g.weight) + log_gauss(x, g);
      lt[t] = std::max(lt[t], l) + std::log1p(std::exp(-std::abs(lt[t] - l)));  // log-sum-exp
    }
    const double top = *std::max_element(lt.begin(), lt.end());
    for (int t = 0; t < kTissues; ++t) evidence[t][v] = static_cast<float>(std::exp(lt[t] - top));
  }
  out.posterior = potts_mean_field(evidence, image.grid, params.mrf_beta, params.mrf_sweeps);
  for (auto& g : classes) {
    g.mean *= scale;
    g.sd *= scale;
  }
  out.classes = std::move(classes);
  return out;
}

}  // namespace brainshift::segmentation
