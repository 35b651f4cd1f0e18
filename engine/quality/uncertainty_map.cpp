#include "quality/uncertainty_map.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <random>

#include "image/distance_map.h"
#include "image/morphology.h"
#include "image/resample.h"
#include "models/carry.h"

namespace brainshift {
namespace {

// A smooth random 3-vector field of unit variance per component with a
// Gaussian correlation of length ell: random Fourier features.
class SmoothNoise {
 public:
  SmoothNoise(std::mt19937_64& rng, double ell_mm) {
    std::normal_distribution<double> k(0.0, 1.0 / ell_mm);
    std::uniform_real_distribution<double> phase(0.0, 2 * M_PI);
    for (auto& c : waves_)
      for (auto& w : c) w = {Eigen::Vector3d(k(rng), k(rng), k(rng)), phase(rng)};
  }
  Eigen::Vector3d at(const Eigen::Vector3d& p) const {
    Eigen::Vector3d out;
    for (int c = 0; c < 3; ++c) {
      double s = 0;
      for (const auto& w : waves_[c]) s += std::cos(w.k.dot(p) + w.phase);
      out[c] = s * std::sqrt(2.0 / kWaves);
    }
    return out;
  }

 private:
  static constexpr int kWaves = 32;
  struct Wave {
    Eigen::Vector3d k;
    double phase;
  };
  std::array<std::array<Wave, kWaves>, 3> waves_;
};

Eigen::Vector3d voxel_centre(const Grid3& g, std::size_t v) {
  const std::size_t nx = g.dims[0], ny = g.dims[1];
  return g.world_mm(static_cast<double>(v % nx), static_cast<double>((v / nx) % ny), static_cast<double>(v / (nx * ny)));
}

// The intraop grid's orientation at about spacing_mm.
Grid3 coarse_grid(const Grid3& fine, double spacing_mm) {
  Grid3 g = fine;
  const Eigen::Vector3d s = fine.spacing_mm();
  Eigen::Vector3d f;
  for (int a = 0; a < 3; ++a) {
    f[a] = std::max(1.0, spacing_mm / s[a]);
    g.dims[a] = std::max(1, static_cast<int>(std::ceil(fine.dims[a] / f[a])));
  }
  g.world_from_voxel.topLeftCorner<3, 3>() = fine.world_from_voxel.topLeftCorner<3, 3>() * f.asDiagonal();
  // Voxel 0 of both grids at the same place; the coarse grid covers the fine one.
  g.world_from_voxel.topRightCorner<3, 1>() = fine.world_from_voxel.topRightCorner<3, 1>();
  return g;
}

// Frobenius norm of the non-rigid part of the pull-back's Jacobian at fine
// voxel f: central differences over the neighbouring voxels, less the
// affine's own (A^-1 - I), which the surface data fixes globally.
double nonrigid_gradient(const VectorImage3& field, std::size_t f, const Eigen::Matrix3d& affine_gradient) {
  const Grid3& g = field.grid;
  const std::size_t nx = g.dims[0], ny = g.dims[1];
  const std::array<std::size_t, 3> ijk{f % nx, (f / nx) % ny, f / (nx * ny)};
  const std::array<std::size_t, 3> stride{1, nx, nx * ny};
  Eigen::Matrix3d d_voxel = Eigen::Matrix3d::Zero();  // column a: du / d(voxel index a)
  for (int a = 0; a < 3; ++a) {
    const std::size_t lo = ijk[a] > 0 ? f - stride[a] : f;
    const std::size_t hi = ijk[a] + 1 < static_cast<std::size_t>(g.dims[a]) ? f + stride[a] : f;
    if (lo == hi) continue;
    d_voxel.col(a) = (field.vectors[hi] - field.vectors[lo]).cast<double>() / static_cast<double>((hi - lo) / stride[a]);
  }
  const Eigen::Matrix3d voxel_from_world = g.voxel_from_world().topLeftCorner<3, 3>();
  return (d_voxel * voxel_from_world - affine_gradient).norm();
}

}  // namespace

double model_error_rms_mm(double nonrigid_mm, double nonrigid_gradient, const UncertaintyParameters& params) {
  return std::sqrt(std::max(0.0, nonrigid_mm * params.resolution_mm * nonrigid_gradient));
}

std::vector<double> propagate_surface_noise(const std::vector<Eigen::Vector3d>& fixed_preop_mm,
                                            const std::vector<double>& sigma_mm, const LinearSolve& solve,
                                            const UncertaintyParameters& params) {
  std::mt19937_64 rng(params.seed);
  std::vector<double> variance;
  const int samples = std::clamp(params.samples, 1, 256);
  std::vector<Eigen::Vector3d> values(fixed_preop_mm.size());
  for (int s = 0; s < samples; ++s) {
    const SmoothNoise noise(rng, params.noise_correlation_mm);
    // Per component sigma / sqrt 3: sigma is the RMS length of the 3-D error.
    for (std::size_t i = 0; i < values.size(); ++i)
      values[i] = noise.at(fixed_preop_mm[i]) * (sigma_mm[i] / std::sqrt(3.0));
    const std::vector<Eigen::Vector3d> nodes = solve(values);
    if (variance.empty()) variance.assign(nodes.size(), 0.0);
    for (std::size_t n = 0; n < nodes.size() && n < variance.size(); ++n) variance[n] += nodes[n].squaredNorm();
  }
  for (auto& v : variance) v = std::sqrt(v / samples);
  return variance;
}

std::vector<double> unseen_surface_rms_mm(const std::vector<Eigen::Vector3d>& fixed_preop_mm,
                                          const std::vector<bool>& unseen, const LinearSolve& solve,
                                          const UncertaintyParameters& params) {
  if (std::find(unseen.begin(), unseen.end(), true) == unseen.end()) return {};
  // How far each unseen node may have gone: its distance to the seen surface,
  // capped. Only seen nodes within the cap matter: they are bucketed in cells
  // of the cap's size, and each unseen node looks in the 27 cells around it.
  const double cap_mm = std::max(params.unseen_shift_mm, 1.0);
  const auto cell = [&](const Eigen::Vector3d& p) {
    return std::array<long, 3>{std::lround(std::floor(p.x() / cap_mm)), std::lround(std::floor(p.y() / cap_mm)),
                               std::lround(std::floor(p.z() / cap_mm))};
  };
  std::map<std::array<long, 3>, std::vector<std::size_t>> seen_in_cell;
  for (std::size_t i = 0; i < unseen.size(); ++i)
    if (!unseen[i]) seen_in_cell[cell(fixed_preop_mm[i])].push_back(i);
  std::vector<double> shift_mm(unseen.size(), 0.0);
  for (std::size_t i = 0; i < unseen.size(); ++i) {
    if (!unseen[i]) continue;
    double nearest2 = params.unseen_shift_mm * params.unseen_shift_mm;
    const auto c = cell(fixed_preop_mm[i]);
    for (long dx = -1; dx <= 1; ++dx)
      for (long dy = -1; dy <= 1; ++dy)
        for (long dz = -1; dz <= 1; ++dz) {
          const auto found = seen_in_cell.find({c[0] + dx, c[1] + dy, c[2] + dz});
          if (found == seen_in_cell.end()) continue;
          for (std::size_t j : found->second)
            nearest2 = std::min(nearest2, (fixed_preop_mm[j] - fixed_preop_mm[i]).squaredNorm());
        }
    shift_mm[i] = std::sqrt(nearest2);
  }
  std::array<std::vector<Eigen::Vector3d>, 3> response;
  for (int a = 0; a < 3; ++a) {
    std::vector<Eigen::Vector3d> values(unseen.size(), Eigen::Vector3d::Zero());
    for (std::size_t i = 0; i < unseen.size(); ++i) values[i] = shift_mm[i] * Eigen::Vector3d::Unit(a);
    response[a] = solve(values);
  }
  const std::size_t nodes = std::min({response[0].size(), response[1].size(), response[2].size()});
  std::vector<double> rms(nodes, 0.0);
  for (std::size_t n = 0; n < nodes; ++n) {
    Eigen::Matrix3d g;
    for (int a = 0; a < 3; ++a) g.col(a) = response[a][n];
    // Largest singular value: the worst direction of the unseen shift.
    const double worst = std::sqrt(std::max(0.0, Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(
                                                     g.transpose() * g, Eigen::EigenvaluesOnly)
                                                     .eigenvalues()
                                                     .maxCoeff()));
    rms[n] = worst / kBand95PerRms;
  }
  return rms;
}

ImageF uncertainty_band_mm(const UncertaintyInput& in, const UncertaintyParameters& params, nlohmann::json* summary) {
  const Grid3& fine = in.intraop_labels.grid;
  const Grid3 coarse = coarse_grid(fine, params.grid_spacing_mm);
  const GridSampler on_fine(fine);
  const Eigen::Matrix4d preop_from_intraop = in.intraop_from_preop.inverse();

  // Where an answer is claimed: the brain with its cavities (ventricles, an
  // enclosed resection), and one voxel beyond its outline, which is itself
  // only known to a voxel (a landmark just outside a segmentation is still
  // in the brain); and where the answer puts preop brain, which the surgeon
  // sees as brain whatever the segmentation said.
  const bool with_warped = in.warped_labels && in.warped_labels->grid.same_geometry(fine);
  Mask region(fine);
  for (std::size_t v = 0; v < region.voxels.size(); ++v)
    region.voxels[v] = in.intraop_labels.voxels[v] != 0 || (with_warped && in.warped_labels->voxels[v] != 0);
  region = dilate(fill_holes(region), fine.spacing_mm().maxCoeff());
  Mask coarse_region(coarse);
  for (std::size_t v = 0; v < coarse.voxel_count(); ++v) {
    std::size_t f;
    coarse_region.voxels[v] = nearest_voxel(fine, on_fine.voxel(voxel_centre(coarse, v)), &f) && region.voxels[f];
  }
  // The map is also evaluated a cell and a half beyond the coarse region (a
  // fine region voxel lies within half a cell of it, its interpolation
  // corners within a cell of that), so the interpolation to the fine grid
  // does not fade it toward the boundary.
  const ImageF outside_mm = distance_to_mask_mm(coarse_region);
  const double reach_mm = 1.5 * coarse.spacing_mm().norm();

  // Preop point of each coarse tissue voxel, its non-rigid displacement and
  // that displacement's gradient.
  const Eigen::Matrix3d affine_gradient = preop_from_intraop.topLeftCorner<3, 3>() - Eigen::Matrix3d::Identity();
  TriSurface points;
  std::vector<std::size_t> where;
  std::vector<double> nonrigid_mm, gradient;
  for (std::size_t v = 0; v < coarse.voxel_count(); ++v) {
    if (!(outside_mm.voxels[v] <= reach_mm)) continue;
    const Eigen::Vector3d x = voxel_centre(coarse, v);
    std::size_t f;
    if (!nearest_voxel(fine, on_fine.voxel(x), &f)) continue;
    const Eigen::Vector3d p = x + in.pullback_field_mm.vectors[f].cast<double>();
    points.vertices_mm.push_back(p);
    where.push_back(v);
    nonrigid_mm.push_back((p - (preop_from_intraop * x.homogeneous()).head<3>()).norm());
    gradient.push_back(nonrigid_gradient(in.pullback_field_mm, f, affine_gradient));
  }
  // The segmentation's quantisation: uniform over a voxel of this size.
  const double quantisation_mm = std::cbrt(fine.spacing_mm().prod()) / std::sqrt(12.0);
  const double model_scale = in.image_refined ? params.image_residual_fraction : 1.0;
  ImageF band_coarse(coarse, 0.f);
  if (!points.vertices_mm.empty()) {
    const ModelBinding b = bind_to_mesh(points, in.preop_mesh);
    for (std::size_t i = 0; i < where.size(); ++i) {
      double noise2 = 0;
      for (int q = 0; q < 4; ++q) {
        const double s = in.node_noise_rms_mm[b.nodes[i][q]];
        noise2 += b.weights[i][q] * s * s;
      }
      const double model = model_scale * model_error_rms_mm(nonrigid_mm[i], gradient[i], params);
      band_coarse.voxels[where[i]] =
          static_cast<float>(kBand95PerRms * std::sqrt(quantisation_mm * quantisation_mm + noise2 + model * model));
    }
  }
  // To the intraop grid, kept to the region.
  ImageF band = resample_linear(band_coarse, fine);
  std::vector<double> inside;
  for (std::size_t v = 0; v < band.voxels.size(); ++v) {
    if (!region.voxels[v]) band.voxels[v] = 0.f;
    else inside.push_back(band.voxels[v]);
  }
  if (summary && !inside.empty()) {
    std::sort(inside.begin(), inside.end());
    double mean = 0;
    for (double d : inside) mean += d / inside.size();
    (*summary)["quantisation_rms_mm"] = quantisation_mm;
    (*summary)["model_error"] = {{"resolution_mm", params.resolution_mm},
                                 {"image_refined", in.image_refined},
                                 {"fraction_kept", model_scale}};
    (*summary)["band95_mm"] = {{"mean", mean},
                               {"median", inside[inside.size() / 2]},
                               {"p95", inside[inside.size() * 95 / 100]},
                               {"max", inside.back()}};
  }
  return band;
}

}  // namespace brainshift
