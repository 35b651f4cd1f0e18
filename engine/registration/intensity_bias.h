#pragma once
// The intensity refinement's intensity model I ~ b(x) f(P) + d
// (registration/intensity_refinement.h): b a low-order polynomial over the
// brain, d a constant, f the preop-to-intraop transfer function: the
// identity for a T1-like pair, or, when a linear relation does not explain
// the image (a T2-like contrast, a compressed low-field one), a smooth 1-D
// function estimated from the joint histogram of the samples. Fitted robustly
// on the bias samples; and whether the fit says the image can be trusted.
// Internal to the refinement.
#include <Eigen/Dense>
#include <optional>
#include <string>
#include <vector>

#include "registration/intensity_lattice.h"
#include "registration/intensity_samples.h"
#include "registration/linear_sampler.h"

namespace brainshift::intensity {

// f(P): binned robust medians of the intraop intensity (divided by the bias)
// per preop intensity bin, smoothed, and interpolated by cubic Hermite
// splines (value and slope continuous: f' drives the Gauss-Newton gradient);
// constant beyond the outer bins. Not required to be monotone.
struct Transfer {
  bool identity = true;
  double first_centre = 0, step = 1;  // of the bins
  std::vector<double> value, slope;   // at the bin centres
  // f(p), and f'(p) in *derivative when not null.
  double at(double p, double* derivative) const;
};

struct BiasModel {
  int degree = 0;
  Eigen::VectorXd coef = Eigen::VectorXd::Ones(1);  // of b(x)
  double offset = 0;                                 // d
  Transfer transfer;                                 // f
  double explained = 0;  // share of the intensity variance the fit explains (weighted R^2)
  double at(const Eigen::Vector3f& q) const;
};

// The bias at the current correction: the degree drops when the data cannot
// support it, and when even a constant b with an offset is not determined (a
// tissue of nearly one intensity: b P and d cannot be told apart) a global
// scale alone is fitted. nullopt when no positive bias fits at all: the
// intraop intensities do not follow the preop T1's (another contrast).
std::optional<BiasModel> fit_bias(const std::vector<Sample>& s, const Lattice& lattice, const LinearSampler& preop,
                                  int degree, double robust_scale);
// The model I ~ b(x) f(P) with f estimated (alternating f and b, bounded
// rounds); nullopt when no positive bias fits.
std::optional<BiasModel> fit_transfer_model(const std::vector<Sample>& s, const Lattice& lattice,
                                            const LinearSampler& preop, int degree, double robust_scale);
// The model the refinement uses: the linear one (f identity) unless it is
// not trusted or the transfer function leaves less than half its unexplained
// variance (the linear relation's misfit then dominates the noise and the
// misalignment together); nullopt when neither fits.
std::optional<BiasModel> fit_intensity_model(const std::vector<Sample>& s, const Lattice& lattice,
                                             const LinearSampler& preop, int degree, double robust_scale,
                                             double min_explained);
std::string describe(const BiasModel& m);
// Stores b(x) in every sample.
void update_bias(std::vector<Sample>& samples, const BiasModel& m);
// Why the image cannot be trusted to move the field, or "" when it can: the
// intensities must follow the preop T1's up to the bias model, and the model
// must explain a fair share of their variance (an unrelated image, or one
// dominated by noise, explains little and would only add noise to the field).
std::string untrusted_image(const std::optional<BiasModel>& bias, double min_explained);

}  // namespace brainshift::intensity
