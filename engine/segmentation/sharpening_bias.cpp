#include "segmentation/sharpening_bias.h"

#include <algorithm>
#include <cmath>
#include <complex>

#include "core/errors.h"
#include "core/parallel.h"
#include "image/gaussian_smooth.h"
#include "image/interpolation.h"
#include "segmentation/bias_field.h"

namespace brainshift::segmentation {
namespace {

using Complex = std::complex<double>;

// In-place radix-2 FFT (n a power of two); inverse without the 1/n.
void fft(std::vector<Complex>& a, bool inverse) {
  const std::size_t n = a.size();
  for (std::size_t i = 1, j = 0; i < n; ++i) {
    std::size_t bit = n >> 1;
    for (; j & bit; bit >>= 1) j ^= bit;
    j ^= bit;
    if (i < j) std::swap(a[i], a[j]);
  }
  const double pi = std::acos(-1.0);
  for (std::size_t len = 2; len <= n; len <<= 1) {
    const double angle = 2 * pi / static_cast<double>(len) * (inverse ? 1 : -1);
    const Complex step(std::cos(angle), std::sin(angle));
    for (std::size_t i = 0; i < n; i += len) {
      Complex w(1, 0);
      for (std::size_t k = 0; k < len / 2; ++k, w *= step) {
        const Complex u = a[i + k], v = a[i + k + len / 2] * w;
        a[i + k] = u + v;
        a[i + k + len / 2] = u - v;
      }
    }
  }
}

// Circular convolution of a real signal with the kernel whose transform is
// kernel_f (both of the padded length).
std::vector<double> convolve(const std::vector<double>& x, const std::vector<Complex>& kernel_f) {
  std::vector<Complex> a(x.begin(), x.end());
  fft(a, false);
  for (std::size_t i = 0; i < a.size(); ++i) a[i] *= kernel_f[i];
  fft(a, true);
  std::vector<double> out(a.size());
  for (std::size_t i = 0; i < a.size(); ++i) out[i] = a[i].real() / static_cast<double>(a.size());
  return out;
}

// N4's histogram sharpening: the expected sharpened value of every bin of
// the histogram of `values` (a lookup over [lo, lo + (bins - 1) * slope]).
struct Sharpened {
  double lo = 0, slope = 1;
  std::vector<double> expected;
  double at(double x) const {
    const double t = std::clamp((x - lo) / slope, 0.0, static_cast<double>(expected.size() - 1));
    const auto i = std::min(static_cast<std::size_t>(t), expected.size() - 2);
    const double f = t - static_cast<double>(i);
    return (1 - f) * expected[i] + f * expected[i + 1];
  }
};

Sharpened sharpen(const std::vector<double>& values, const SharpeningBiasParameters& p) {
  const auto [lo_it, hi_it] = std::minmax_element(values.begin(), values.end());
  Sharpened s;
  const int bins = std::max(p.bins, 8);
  s.lo = *lo_it;
  s.slope = std::max(*hi_it - *lo_it, 1e-9) / (bins - 1);
  std::size_t padded = 1;
  while (padded < static_cast<std::size_t>(bins)) padded <<= 1;
  padded <<= 1;
  const std::size_t offset = (padded - static_cast<std::size_t>(bins)) / 2;
  // Each value split between its two nearest bins.
  std::vector<double> histogram(padded, 0.0);
  for (double v : values) {
    const double t = (v - s.lo) / s.slope;
    const auto i = std::min(static_cast<std::size_t>(t), static_cast<std::size_t>(bins - 2));
    const double f = std::clamp(t - static_cast<double>(i), 0.0, 1.0);
    histogram[offset + i] += 1 - f;
    histogram[offset + i + 1] += f;
  }
  // The blurring kernel, centred on bin 0 (wrapped), and its Wiener inverse.
  const double sigma_bins = p.fwhm / s.slope / (2 * std::sqrt(2 * std::log(2.0)));
  std::vector<Complex> kernel(padded, 0.0);
  double sum = 0;
  for (std::size_t i = 0; i < padded; ++i) {
    const double d = static_cast<double>(i <= padded / 2 ? i : padded - i);
    sum += (kernel[i] = std::exp(-0.5 * d * d / (sigma_bins * sigma_bins))).real();
  }
  for (auto& k : kernel) k /= sum;
  fft(kernel, false);
  std::vector<Complex> wiener(padded);
  for (std::size_t i = 0; i < padded; ++i)
    wiener[i] = std::conj(kernel[i]) / (std::norm(kernel[i]) + p.wiener_noise);
  std::vector<double> u = convolve(histogram, wiener);
  for (auto& x : u) x = std::max(x, 0.0);
  std::vector<double> weighted(padded);
  for (std::size_t i = 0; i < padded; ++i)
    weighted[i] = u[i] * (s.lo + (static_cast<double>(i) - static_cast<double>(offset)) * s.slope);
  const std::vector<double> numerator = convolve(weighted, kernel), denominator = convolve(u, kernel);
  s.expected.resize(static_cast<std::size_t>(bins));
  for (std::size_t i = 0; i < s.expected.size(); ++i) {
    const double centre = s.lo + static_cast<double>(i) * s.slope;
    const double d = denominator[offset + i];
    s.expected[i] = d > 1e-12 ? numerator[offset + i] / d : centre;
  }
  return s;
}

// The coarse grid the field lives on: node n along an axis at voxel
// n * step (step in voxels, not necessarily whole), at least two nodes and
// enough to cover the image. A point's place on it is the project's
// trilinear cell (image/interpolation.h), clamped onto the nodes.
struct FieldGrid {
  Grid3 nodes;
  Eigen::Vector3d step;
  std::size_t size() const { return nodes.voxel_count(); }
  TrilinearCell<double> cell_of(const Eigen::Vector3d& voxel) const {
    TrilinearCell<double> c;
    trilinear_cell<TrilinearEdge::kClamp>(nodes, Eigen::Vector3d(voxel.cwiseQuotient(step)), &c);
    return c;
  }
};

double interpolate(const TrilinearCell<double>& c, const std::vector<double>& field) {
  return trilinear_blend(trilinear_corners<double>(field.data(), c), c);
}

// The transpose of interpolate: value spread onto the cell's corners by
// their trilinear weights (corner order as trilinear_corners).
void splat(const TrilinearCell<double>& c, double value, ImageF& nodes) {
  for (int n = 0; n < 8; ++n) {
    double w = 1;
    std::size_t at = c.origin;
    for (int a = 0; a < 3; ++a) {
      const bool up = (n >> a) & 1;
      w *= up ? c.t[static_cast<std::size_t>(a)] : 1 - c.t[static_cast<std::size_t>(a)];
      if (up) at += c.step[static_cast<std::size_t>(a)];
    }
    nodes.voxels[at] += static_cast<float>(w * value);
  }
}

// The image's region voxels on a lattice of stride voxels, brighter than
// floor_fraction of their median (air and noise are not tissue): their log
// intensities and their weights on the field's nodes.
struct Samples {
  std::vector<TrilinearCell<double>> at;
  std::vector<double> log_value;
  std::vector<std::array<int, 3>> voxel;
};

Samples lattice_samples(const ImageF& image, const Mask& region, const std::array<int, 3>& stride,
                        const FieldGrid& f, double floor_fraction) {
  const Grid3& g = image.grid;
  std::vector<std::array<int, 3>> lattice;
  std::vector<float> values;
  for (int k = 0; k < g.dims[2]; k += stride[2])
    for (int j = 0; j < g.dims[1]; j += stride[1])
      for (int i = 0; i < g.dims[0]; i += stride[0])
        if (region.at(i, j, k)) {
          lattice.push_back({i, j, k});
          values.push_back(image.at(i, j, k));
        }
  Samples s;
  if (lattice.empty()) return s;
  std::vector<float> sorted = values;
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(sorted.size() / 2), sorted.end());
  const double floor = std::max(floor_fraction * sorted[sorted.size() / 2], 0.0);
  for (std::size_t n = 0; n < lattice.size(); ++n) {
    if (!(values[n] > floor)) continue;
    s.at.push_back(f.cell_of(Eigen::Vector3d(lattice[n][0], lattice[n][1], lattice[n][2])));
    s.voxel.push_back(lattice[n]);
    s.log_value.push_back(std::log(static_cast<double>(values[n])));
  }
  return s;
}

// N4's iterations on the nodes: field += relaxation x the smoothed residual
// of the samples' sharpening, mean 0 over the samples.
std::vector<double> iterate_field(const Samples& s, const FieldGrid& f, const Eigen::Vector3d& sigma_nodes,
                                  const SharpeningBiasParameters& p, SharpeningBias& out) {
  ImageF weight(f.nodes, 0.f);
  for (const auto& c : s.at) splat(c, 1.0, weight);
  gaussian_smooth_voxels(weight, sigma_nodes);
  std::vector<double> field(f.size(), 0.0), step(f.size(), 0.0), corrected(s.at.size());
  for (int it = 0; it < p.max_iterations; ++it) {
    for (std::size_t n = 0; n < s.at.size(); ++n) corrected[n] = s.log_value[n] - interpolate(s.at[n], field);
    const Sharpened sharp = sharpen(corrected, p);
    ImageF residual(f.nodes, 0.f);
    for (std::size_t n = 0; n < s.at.size(); ++n) splat(s.at[n], corrected[n] - sharp.at(corrected[n]), residual);
    gaussian_smooth_voxels(residual, sigma_nodes);
    for (std::size_t c = 0; c < f.size(); ++c)
      step[c] = weight.voxels[c] > 1e-6f ? p.relaxation * residual.voxels[c] / weight.voxels[c] : 0.0;
    double change2 = 0, mean = 0;
    for (std::size_t c = 0; c < f.size(); ++c) field[c] += step[c];
    for (const auto& c : s.at) {
      const double d = interpolate(c, step);
      change2 += d * d;
      mean += interpolate(c, field);
    }
    mean /= static_cast<double>(s.at.size());
    for (auto& x : field) x -= mean;
    out.iterations = it + 1;
    if (std::sqrt(change2 / static_cast<double>(s.at.size())) < p.tolerance) {
      out.converged = true;
      break;
    }
  }
  for (const auto& c : s.at) out.max_abs_log_bias = std::max(out.max_abs_log_bias, std::abs(interpolate(c, field)));
  return field;
}

// The nodes' field at every voxel of g, trilinear.
void field_on_voxels(const FieldGrid& f, const std::vector<double>& field, const Grid3& g, std::vector<float>& out) {
  for_each_voxel_on_both_cores(g.dims, [&](std::size_t v, int i, int j, int k) {
    out[v] = static_cast<float>(interpolate(f.cell_of(Eigen::Vector3d(i, j, k)), field));
  });
}

// What of the field at the samples a log-polynomial of degree 2 (the
// classes' own bias model, bias_field.h) leaves: rms of the residual.
double beyond_polynomial_rms(const Samples& s, const std::vector<double>& field, const Grid3& g) {
  std::vector<double> value(s.at.size()), weight(s.at.size(), 1.0);
  for (std::size_t n = 0; n < s.at.size(); ++n) value[n] = interpolate(s.at[n], field);
  LogBiasField quadratic(g, 2);
  if (!quadratic.fit(s.voxel, value, weight)) return 0.0;
  double mean = 0, sum2 = 0;
  std::vector<double> r(s.at.size());
  for (std::size_t n = 0; n < s.at.size(); ++n)
    mean += r[n] = value[n] - quadratic.log_bias(s.voxel[n][0], s.voxel[n][1], s.voxel[n][2]);
  mean /= static_cast<double>(r.size());
  for (double x : r) sum2 += (x - mean) * (x - mean);
  return std::sqrt(sum2 / static_cast<double>(r.size()));
}

}  // namespace

SharpeningBias sharpening_log_bias(const ImageF& image, const Mask& region, const SharpeningBiasParameters& p) {
  if (!image.grid.same_geometry(region.grid)) throw InputError("sharpening bias: image and region on different grids");
  if (!(p.lattice_mm > 0) || !(p.smoothing_mm > 0) || !(p.fwhm > 0) || !(p.relaxation > 0) || p.max_iterations < 0)
    throw InputError("sharpening bias: lattice, smoothing, FWHM and relaxation must be positive");
  const Grid3& g = image.grid;
  SharpeningBias out;
  out.log_bias.assign(g.voxel_count(), 0.f);
  // Samples: single voxels on a lattice of about lattice_mm. The field: a
  // grid of nodes 2.5 to a smoothing sigma apart (a Gaussian of sigma is
  // sampled well at that spacing), onto which the samples' residuals are
  // spread trilinearly and smoothed (normalised convolution).
  const Eigen::Vector3d spacing = g.spacing_mm();
  std::array<int, 3> stride{};
  FieldGrid f;
  Eigen::Vector3d sigma_nodes;
  for (int a = 0; a < 3; ++a) {
    stride[a] = std::max(1, static_cast<int>(std::lround(p.lattice_mm / spacing[a])));
    f.step[a] = std::max(p.smoothing_mm / 2.5 / spacing[a], 1.0);
    f.nodes.dims[a] = std::max(2, static_cast<int>(std::ceil((g.dims[a] - 1) / f.step[a])) + 1);
    sigma_nodes[a] = p.smoothing_mm / (f.step[a] * spacing[a]);
  }
  const Samples samples = lattice_samples(image, region, stride, f, p.floor_fraction);
  out.samples = samples.at.size();
  if (samples.at.size() < p.min_samples) return out;
  const std::vector<double> field = iterate_field(samples, f, sigma_nodes, p, out);
  out.beyond_polynomial_rms = beyond_polynomial_rms(samples, field, g);
  // A field beyond what coils do found something else (a lesion or a
  // contrast the histogram cannot place): not used.
  if (out.max_abs_log_bias > p.max_log_bias) {
    out.discarded = true;
    return out;
  }
  field_on_voxels(f, field, g, out.log_bias);
  return out;
}

nlohmann::json to_json(const SharpeningBias& b) {
  return {{"samples", b.samples},
          {"discarded", b.discarded},
          {"beyond_polynomial_rms", b.beyond_polynomial_rms},
          {"iterations", b.iterations},
          {"converged", b.converged},
          {"max_abs_log_bias", b.max_abs_log_bias}};
}

}  // namespace brainshift::segmentation
