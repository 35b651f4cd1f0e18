#include "segmentation/tissue_em.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

#include "core/errors.h"
#include "core/parallel.h"
#include "segmentation/bias_field.h"
#include "segmentation/em_initial_classes.h"
#include "segmentation/em_samples.h"
#include "segmentation/potts.h"

namespace brainshift::segmentation {

const GaussianClass* heaviest_class(const std::vector<GaussianClass>& classes, Tissue t) {
  const GaussianClass* best = nullptr;
  for (const auto& c : classes)
    if (c.tissue == t && (!best || c.weight > best->weight)) best = &c;
  return best;
}

namespace {

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
