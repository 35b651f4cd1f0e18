#include "segmentation/em_initial_classes.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <utility>

namespace brainshift::segmentation {
namespace {

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

}  // namespace

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

}  // namespace brainshift::segmentation
