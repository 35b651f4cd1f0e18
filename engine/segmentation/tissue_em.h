#pragma once
// Atlas-prior EM classification of an MR image into three tissues: brain
// parenchyma, ventricular fluid and everything outside the brain (fluid
// under the craniotomy, skull, scalp, air), in the manner of Van Leemput et
// al. (1999) and of the adaptive-template classification of Warfield et al.:
//   - a spatially varying prior per voxel (tissue_prior.h) says where each
//     tissue is expected; the image says what each looks like;
//   - each tissue is a small mixture of Gaussians over the bias-corrected
//     intensity (grey/white matter; the outside's fluid, bone and fat), fitted
//     from the prior alone: nothing assumes a T1 ordering of the intensities,
//     so a T2-like image (bright fluid) is fitted the same way;
//   - a multiplicative bias, log-polynomial (bias_field.h), fitted between the
//     EM steps on the residual log ratio image / expected intensity;
//   - after the fit, a light Potts smoothing (mean field, 6-neighbourhood)
//     on the tissue posteriors.
// Parameters are fitted on a regular subsample of the voxels (a few tens of
// thousands determine a dozen numbers to well below the noise), the posterior
// is then computed on every voxel. Every loop is bounded.
#include <array>
#include <cstddef>
#include <optional>
#include <vector>

#include "core/image.h"
#include "segmentation/bias_field.h"
#include "segmentation/tissue_prior.h"

namespace brainshift::segmentation {

struct EmParameters {
  // Gaussians per tissue: parenchyma (grey, white), ventricular fluid, and
  // outside the brain (air, bone, fluid, fat/scalp). The outside gets one
  // more, the fluid around the brain held to the ventricles' fluid
  // (GaussianClass::surface_fluid), whenever it has more than one.
  std::array<int, kTissues> classes{2, 1, 4};
  int bias_degree = 2;
  int max_iterations = 30;
  // Converged when the mean log-likelihood per sample changes by less than
  // this between iterations (nats; far below what moves a class mean).
  double tolerance = 1e-4;
  std::size_t fit_samples = 60000;
  // The ventricles' class stays where it was started (from the brain's fluid,
  // tissue_em.cpp fluid_class) instead of being re-estimated: set while their
  // prior may lie several mm off (after the head's alignment alone), where
  // the EM would spread it over the white matter the prior holds instead.
  bool fixed_ventricle_class = false;
  double mrf_beta = 0.35;  // Potts coupling per face neighbour (0: no smoothing)
  int mrf_sweeps = 3;
};

struct GaussianClass {
  Tissue tissue = Tissue::parenchyma;
  double mean = 0;    // bias-corrected intensity, in the image's units
  double sd = 0;
  double weight = 0;  // share within its tissue
  // Share within its tissue next to the brain's outline (in_surface_band),
  // <= 0: weight. Only the outside's fluid class of a bright-fluid image has
  // one of its own (tissue_em.cpp hold_surface_fluid); the other outside
  // classes there keep their proportions of what it leaves.
  double band_weight = 0;
  // The outside's class of the fluid around the brain (subarachnoid CSF,
  // fluid under the craniotomy): started at the ventricles' fluid, and held
  // to it where the fluid is the brightest tissue.
  bool surface_fluid = false;
};

// The class of tissue t with the largest weight (the first of equals);
// nullptr when t has none.
const GaussianClass* heaviest_class(const std::vector<GaussianClass>& classes, Tissue t);

// A parenchyma class holding at least this share of the parenchyma is a
// major one (a tissue of the brain, not a partial-volume class): the
// ventricles' contrast (intraop_segmentation.cpp) and the fluid rim's cortex
// (fluid_rim.h) are measured against the major classes only.
inline constexpr double kMajorClassWeight = 1.0 / 6;

// A bright-fluid (T2-like) contrast: the fluid's heaviest class brighter
// than the parenchyma's heaviest (the bulk of the brain's tissue). Not
// "than every parenchyma class": a class spanning the brain's own bright
// tissue (sulcal fluid, oedema) may reach past the fluid's mean.
bool fluid_is_bright(const std::vector<GaussianClass>& classes);

struct EmResult {
  std::vector<GaussianClass> classes;
  std::array<std::vector<float>, kTissues> posterior;  // per voxel, after the smoothing; sum to 1
  std::vector<float> bias;  // multiplicative, per voxel (mean log 1 over the brain)
  // The fitted log bias itself, on the fitted image's grid (absent when the
  // classes were given, classify_with_classes).
  std::optional<LogBiasField> bias_field;
  int iterations = 0;
  bool converged = false;
  double mean_log_likelihood = 0;
  std::size_t samples = 0;  // the fit's subsample (at most EmParameters::fit_samples; 0 when given the classes)
  // Parenchyma classes the fit gave up because one was the fluid taken for
  // tissue (fit_tissue_mixture).
  int parenchyma_classes_dropped = 0;
};

// image and prior on the same grid. InputError when the prior has no brain or
// the image is constant. On a dark-fluid image a parenchyma class within a
// fluid sd above the fluid's mean (or below it) is the fluid taken for
// tissue: the fit is made again with one parenchyma class fewer
// (EmResult::parenchyma_classes_dropped).
EmResult fit_tissue_mixture(const ImageF& image, const TissuePrior& prior, const EmParameters& params);

// The posterior (evidence and Potts smoothing, as after a fit) of classes
// already fitted to the same image (image units: fit_tissue_mixture's
// classes) under another prior, with log_bias the log of the fitted bias per
// voxel of image's grid: no fit. A re-match round (the prior narrowed once
// the non-rigid estimate carries the labels) sees the same scanner, coil and
// tissues as the round that fitted them. iterations 0.
EmResult classify_with_classes(const ImageF& image, const TissuePrior& prior, const std::vector<GaussianClass>& classes,
                               const std::vector<float>& log_bias, const EmParameters& params);

}  // namespace brainshift::segmentation
