#pragma once
// The intensity refinement's bias model I ~ b(x) P + d (registration/intensity_refinement.h):
// b a low-order polynomial over the brain, d a constant, fitted robustly on
// the bias samples; and whether the fit says the image can be trusted.
// Internal to the refinement.
#include <Eigen/Dense>
#include <optional>
#include <string>
#include <vector>

#include "registration/intensity_lattice.h"
#include "registration/intensity_samples.h"
#include "registration/linear_sampler.h"

namespace brainshift::intensity {

struct BiasModel {
  int degree = 0;
  Eigen::VectorXd coef = Eigen::VectorXd::Ones(1);  // of b(x)
  double offset = 0;                                 // d
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
std::string describe(const BiasModel& m);
// Stores b(x) in every sample.
void update_bias(std::vector<Sample>& samples, const BiasModel& m);
// Why the image cannot be trusted to move the field, or "" when it can: the
// intensities must follow the preop T1's up to the bias model, and the model
// must explain a fair share of their variance (an unrelated image, or one
// dominated by noise, explains little and would only add noise to the field).
std::string untrusted_image(const std::optional<BiasModel>& bias, double min_explained);

}  // namespace brainshift::intensity
