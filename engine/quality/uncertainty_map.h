#pragma once
// How far the served answer can be trusted, voxel by voxel: the radius (mm)
// of the 95 % band around the matched preop point x + u(x), on the intraop
// grid (uncertainty.nii.gz). It covers the brain with its cavities and one
// voxel beyond the segmented outline (which is only known to a voxel); 0
// farther out, where no answer is claimed.
//
// Two independent sources, added in quadrature (DESIGN.md, "Uncertainty map"):
//  1. The surface data's noise, propagated through the elastic model by Monte
//     Carlo. Each matched surface node's displacement is uncertain by its own
//     measured residual (distance of the matched node to the intraop boundary)
//     and the segmentation's voxel quantisation (spacing / sqrt 12 across the
//     thickest voxel); the noise is spatially correlated like a segmenter's
//     (random Fourier features of a Gaussian process, correlation length
//     noise_correlation_mm). The model is linear, so a sample's effect on the
//     field is the solve of the noise alone: one warm pair of triangular
//     solves each. The node variance is carried to the voxels through the
//     mesh (barycentric, at the preop point of each voxel).
//  2. The model's own error where no data reaches: a fraction of the local
//     non-rigid displacement (a linear elastic model with generic material
//     recovers 75-85 % of measured shift in the published validations), grown
//     with the distance from the nearest boundary data (outline, ventricle
//     wall, cavity) over depth_scale_mm.
// The band radius is the 95 % quantile of a 3-D isotropic Gaussian error of
// that RMS: 2.80 / sqrt(3) = 1.61 times it.
#include <cstdint>
#include <functional>
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "core/image.h"
#include "core/tet_mesh.h"

namespace brainshift {

struct UncertaintyParameters {
  bool enabled = true;
  int samples = 12;                   // Monte Carlo right-hand sides
  double noise_correlation_mm = 10;   // correlation length of the surface noise
  double model_error_fraction = 0.25; // of the local non-rigid displacement, far from data
  double depth_scale_mm = 10;         // distance over which that error reaches its full size
  double grid_spacing_mm = 3;         // the map is computed this coarse, then interpolated
  std::uint64_t seed = 19;
};

// Fixed-node values (in the FEM's fixed-node order) -> node displacements.
using LinearSolve = std::function<std::vector<Eigen::Vector3d>(const std::vector<Eigen::Vector3d>&)>;

// RMS (3-D) displacement at every mesh node caused by surface noise of RMS
// sigma_mm[i] at fixed node i (preop position fixed_preop_mm[i]).
std::vector<double> propagate_surface_noise(const std::vector<Eigen::Vector3d>& fixed_preop_mm,
                                            const std::vector<double>& sigma_mm, const LinearSolve& solve,
                                            const UncertaintyParameters& params);

struct UncertaintyInput {
  const TetMesh& preop_mesh;
  const std::vector<double>& node_noise_rms_mm;  // propagate_surface_noise
  const VectorImage3& pullback_field_mm;         // the served field
  Eigen::Matrix4d intraop_from_preop;
  const LabelImage& intraop_labels;
  std::vector<std::uint16_t> tissue_labels;      // labels that are tissue (not cavity, not 0)
};

// The 95 % band radius (mm) on the intraop grid; summary (optional) gets its
// statistics over the brain.
ImageF uncertainty_band_mm(const UncertaintyInput& in, const UncertaintyParameters& params,
                           nlohmann::json* summary = nullptr);

// 2.80 / sqrt(3): the 95 % radius of an isotropic 3-D Gaussian per unit of its RMS length.
inline constexpr double kBand95PerRms = 1.6140;

}  // namespace brainshift
