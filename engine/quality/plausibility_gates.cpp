#include "quality/plausibility_gates.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "image/resample.h"

namespace brainshift {
namespace {

std::string fixed(double v, int digits = 3) {
  std::ostringstream s;
  s.precision(digits);
  s << std::fixed << v;
  return s.str();
}

GateResult untested(const std::string& name, const std::string& why) {
  GateResult g;
  g.name = name;
  g.tested = false;
  g.detail = why;
  return g;
}

double affine_det(const Eigen::Matrix4d& A) { return A.topLeftCorner<3, 3>().determinant(); }

}  // namespace

std::string PlausibilityReport::first_failure() const {
  for (const auto& g : gates_)
    if (g.tested && !g.passed)
      return "plausibility gate " + g.name + ": " + g.detail + " (value " + fixed(g.value) + ", limit " + g.limit + ")";
  return {};
}

nlohmann::json PlausibilityReport::to_json() const {
  nlohmann::json out = nlohmann::json::object();
  bool all = true;
  for (const auto& g : gates_) {
    nlohmann::json j = {{"tested", g.tested}, {"detail", g.detail}};
    if (g.tested) {
      j["value"] = g.value;
      j["limit"] = g.limit;
      j["passed"] = g.passed;
      all = all && g.passed;
    }
    for (const auto& [k, v] : g.extra.items()) j[k] = v;
    out[g.name] = std::move(j);
  }
  // No gate run (an earlier stage failed, or the gates are off) is no pass.
  out["all_passed"] = all && !gates_.empty();
  return out;
}

// The part of the preop brain the affine places inside the intraop grid
// (voxel centres within half a voxel of its border), from every second
// voxel along each axis: a fraction good to a fraction of a percent, and
// extents good to a millimetre.
PreopInView preop_in_view(const LabelImage& preop, const Grid3& intraop, const Eigen::Matrix4d& intraop_from_preop) {
  const Eigen::Matrix4d voxel_from_preop_voxel = intraop.voxel_from_world() * intraop_from_preop * preop.grid.world_from_voxel;
  PreopInView out;
  std::size_t all = 0;
  for (int k = 0; k < preop.grid.dims[2]; k += 2)
    for (int j = 0; j < preop.grid.dims[1]; j += 2)
      for (int i = 0; i < preop.grid.dims[0]; i += 2) {
        if (preop.at(i, j, k) == 0) continue;
        ++all;
        const Eigen::Vector4d ijk(i, j, k, 1);
        const Eigen::Vector3d v = (voxel_from_preop_voxel * ijk).head<3>();
        bool inside = true;
        for (int a = 0; a < 3; ++a) inside = inside && v[a] >= -0.5 && v[a] <= intraop.dims[a] - 0.5;
        if (inside) out.points_preop_mm.push_back((preop.grid.world_from_voxel * ijk).head<3>().cast<float>());
      }
  out.fraction = all ? static_cast<double>(out.points_preop_mm.size()) / static_cast<double>(all) : 1.0;
  return out;
}

double PreopInView::extent_mm(const Eigen::Vector3d& direction_preop) const {
  if (points_preop_mm.size() < 2) return 0.0;
  const Eigen::Vector3f d = direction_preop.normalized().cast<float>();
  std::vector<float> along(points_preop_mm.size());
  for (std::size_t n = 0; n < along.size(); ++n) along[n] = points_preop_mm[n].dot(d);
  // Percentiles, not the ends: a stray labelled voxel is not the brain's extent.
  const auto at = [&](double q) {
    auto it = along.begin() + static_cast<std::ptrdiff_t>(q * static_cast<double>(along.size() - 1));
    std::nth_element(along.begin(), it, along.end());
    return static_cast<double>(*it);
  };
  const double low = at(0.01);
  return at(0.99) - low;
}

GateResult volume_gate(double intraop_ml, double preop_in_view_ml, const Eigen::Matrix4d& A,
                       const PlausibilityLimits& limits, double open_fluid_ml) {
  if (preop_in_view_ml <= 0) return untested("volume", "no preop brain volume in the field of view");
  GateResult g;
  g.name = "volume";
  const double mapped_ml = affine_det(A) * preop_in_view_ml;
  const double held_ml = intraop_ml + open_fluid_ml;
  g.value = std::abs(held_ml / mapped_ml - 1.0);
  g.limit = "<= " + fixed(limits.max_volume_change);
  g.passed = g.value <= limits.max_volume_change;
  g.detail = "intraop brain " + fixed(intraop_ml, 1) + " ml" +
             (open_fluid_ml > 0 ? " + " + fixed(open_fluid_ml, 1) + " ml of fluid where the brain was" : "") +
             " against the preop brain in the field of view mapped by the affine " + fixed(mapped_ml, 1) +
             " ml (relative change)";
  g.extra = {{"intraop_ml", intraop_ml}, {"open_fluid_ml", open_fluid_ml}, {"preop_mapped_ml", mapped_ml}};
  return g;
}

GateResult ventricle_volume_gate(double intraop_ml, double preop_ml, const Eigen::Matrix4d& A,
                                 const PlausibilityLimits& limits) {
  if (preop_ml <= 0 || intraop_ml <= 0) return untested("ventricle_volume", "ventricles absent from one of the scans");
  GateResult g;
  g.name = "ventricle_volume";
  const double mapped_ml = affine_det(A) * preop_ml;
  // Symmetric in the ratio, but only growth is refused: shrinking ventricles
  // (drained CSF, a segmenter losing horns) is reported, never a reason to
  // withhold an answer; a label grown over brain tissue is.
  g.value = intraop_ml / mapped_ml;
  g.limit = "<= " + fixed(limits.max_ventricle_volume_ratio, 2);
  g.passed = g.value <= limits.max_ventricle_volume_ratio;
  g.detail = "intraop ventricles " + fixed(intraop_ml, 1) + " ml against the preop's mapped by the affine " +
             fixed(mapped_ml, 1) + " ml (ratio)";
  return g;
}

// A scan passes the field-of-view check only with at least half the brain in
// view (min_intraop_brain_fraction), which is at least ~60 mm of a 120-170 mm
// brain along any direction: an extent below 50 mm (an affine that maps the
// preop away from the scan it was fitted to) is not read as a licence for any
// stretch.
constexpr double kLeastExtentMm = 50.0;

double affine_stretch_limit(double extent_mm, const PlausibilityLimits& limits) {
  return limits.affine_stretch_base +
         limits.affine_sink_share * limits.max_sink_depth_mm / std::max(extent_mm, kLeastExtentMm);
}

double affine_sink_limit(double extent_mm, const PlausibilityLimits& limits) {
  return limits.affine_stretch_base + limits.max_sink_depth_mm / std::max(extent_mm, kLeastExtentMm);
}

namespace {

// Rotation part of the polar decomposition L = R S, from L's SVD.
Eigen::Matrix3d polar_rotation(const Eigen::JacobiSVD<Eigen::Matrix3d>& svd) {
  Eigen::Matrix3d R = svd.matrixU() * svd.matrixV().transpose();
  if (R.determinant() < 0) R = -R;
  return R;
}

}  // namespace

Eigen::Matrix4d rigid_part(const Eigen::Matrix4d& A, const Eigen::Vector3d& centre_mm) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(A.topLeftCorner<3, 3>(), Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d R = polar_rotation(svd);
  Eigen::Matrix4d out = Eigen::Matrix4d::Identity();
  out.topLeftCorner<3, 3>() = R;
  out.block<3, 1>(0, 3) = (A * centre_mm.homogeneous()).head<3>() - R * centre_mm;
  return out;
}

bool refuses_labels_geometry(const PlausibilityReport& report) {
  for (const GateResult& g : report.gates())
    if (g.tested && !g.passed) return g.name == "volume" || g.name == "affine_stretch";
  return false;
}

std::vector<GateResult> affine_gates(const Eigen::Matrix4d& A, const PlausibilityLimits& limits,
                                     const ExtentAlong& visible_extent_mm, double sink_gap_ml) {
  const Eigen::Matrix3d L = A.topLeftCorner<3, 3>();
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(L, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Vector3d s = svd.singularValues();
  GateResult stretch;
  stretch.name = "affine_stretch";
  // Each principal stretch against its own direction's limit; the gate's
  // value and limit are those of the direction nearest its limit.
  nlohmann::json directions = nlohmann::json::array();
  double worst_ratio = -1, worst = 0, worst_limit = 0;
  for (int i = 0; i < 3; ++i) {
    const Eigen::Vector3d v = svd.matrixV().col(i);
    const double extent = visible_extent_mm(v);
    // The singular values come largest first: s[2] is the most compressed
    // direction, the one a sinking the image shows may take in full.
    const bool sink = i == 2 && s[i] < 1.0 && sink_gap_ml > 0;
    const double limit = sink ? affine_sink_limit(extent, limits) : affine_stretch_limit(extent, limits);
    const double deviation = std::max(s[i] - 1.0, 1.0 / s[i] - 1.0);
    directions.push_back({{"stretch", s[i]}, {"direction_preop", {v[0], v[1], v[2]}}, {"brain_extent_in_view_mm", extent},
                          {"limit", limit}, {"sink_shown", sink}});
    if (deviation / limit > worst_ratio) {
      worst_ratio = deviation / limit;
      worst = deviation;
      worst_limit = limit;
    }
  }
  // A mirror (det < 0) can never be a head moving: infinite deviation.
  if (L.determinant() <= 0) worst = INFINITY;
  stretch.value = worst;
  stretch.limit = "<= " + fixed(worst_limit);
  stretch.passed = worst <= worst_limit;
  stretch.detail = "largest principal stretch of the affine away from 1, against the limit its direction's brain "
                   "extent in view allows (scale and shear; the same head)";
  stretch.extra = {{"principal_stretches", {s[0], s[1], s[2]}}, {"determinant", L.determinant()},
                   {"directions", directions}};

  const Eigen::Matrix3d R = polar_rotation(svd);
  const double angle_deg = Eigen::AngleAxisd(R).angle() * 180.0 / M_PI;
  GateResult rotation;
  rotation.name = "head_rotation";
  rotation.value = angle_deg;
  rotation.limit = "<= " + fixed(limits.max_head_rotation_deg, 1);
  rotation.passed = angle_deg <= limits.max_head_rotation_deg;
  rotation.detail = "rotation of the head between the scans (degrees)";
  return {stretch, rotation};
}

std::vector<GateResult> field_gates(const TetMesh& mesh, const std::vector<Eigen::Vector3d>& w,
                                    const PlausibilityLimits& limits) {
  double largest_mm = 0;
  for (const auto& x : w) largest_mm = std::max(largest_mm, x.norm());
  GateResult largest;
  largest.name = "max_displacement";
  largest.value = largest_mm;
  largest.limit = "<= " + fixed(limits.max_displacement_mm, 1) + " mm";
  largest.passed = largest.value <= limits.max_displacement_mm;
  largest.detail = "largest non-rigid displacement (mm, beyond the affine)";

  // RMS small strain sym(grad w) over the mesh volume, w linear in each tet.
  double strain2 = 0, volume = 0;
  for (std::size_t t = 0; t < mesh.tets.size(); ++t) {
    const auto& n = mesh.tets[t];
    Eigen::Matrix3d P, W;
    for (int c = 0; c < 3; ++c) {
      P.col(c) = mesh.nodes_mm[n[c + 1]] - mesh.nodes_mm[n[0]];
      W.col(c) = w[n[c + 1]] - w[n[0]];
    }
    const double v = std::abs(P.determinant()) / 6.0;
    if (v <= 0) continue;
    const Eigen::Matrix3d G = W * P.inverse();
    const Eigen::Matrix3d e = 0.5 * (G + G.transpose());
    strain2 += v * e.squaredNorm();
    volume += v;
  }
  GateResult strain;
  strain.name = "strain";
  strain.value = volume > 0 ? std::sqrt(strain2 / volume) : 0.0;
  strain.limit = "<= " + fixed(limits.max_rms_strain);
  strain.passed = strain.value <= limits.max_rms_strain;
  strain.detail = "RMS small strain of the non-rigid field over the brain (strain energy per volume / shear modulus)";
  return {largest, strain};
}

double squared_correlation(const std::vector<double>& a, const std::vector<double>& b) {
  const std::size_t n = std::min(a.size(), b.size());
  if (n < 3) return 0;
  double ma = 0, mb = 0;
  for (std::size_t i = 0; i < n; ++i) ma += a[i], mb += b[i];
  ma /= n, mb /= n;
  double sab = 0, saa = 0, sbb = 0;
  for (std::size_t i = 0; i < n; ++i) {
    sab += (a[i] - ma) * (b[i] - mb);
    saa += (a[i] - ma) * (a[i] - ma);
    sbb += (b[i] - mb) * (b[i] - mb);
  }
  return saa > 0 && sbb > 0 ? sab * sab / (saa * sbb) : 0.0;
}

GateResult image_gate(const ImageF& preop_t1, const ImageF& intraop_t1, const Mask& brain, const VectorImage3& u,
                      const Eigen::Matrix4d& A, const PlausibilityLimits& limits) {
  const std::size_t n = brain.voxels.size();
  if (intraop_t1.voxels.size() != n || u.vectors.size() != n) return untested("image", "no intraop image");
  // About 60k samples: the correlation's sampling error (~(1-r^2)/sqrt(n))
  // stays far below the tolerance, at a few ms.
  std::size_t inside = 0;
  for (auto m : brain.voxels) inside += m != 0;
  const std::size_t stride = std::max<std::size_t>(1, inside / 60000);
  const GridSampler preop(preop_t1.grid);
  const Eigen::Matrix4d preop_from_intraop = A.inverse();
  const Grid3& g = brain.grid;
  std::vector<double> fixed_v, warped_v, affine_v;
  std::size_t seen = 0;
  for (std::size_t v = 0; v < n; ++v) {
    if (!brain.voxels[v] || (seen++ % stride) != 0) continue;
    const int i = static_cast<int>(v % g.dims[0]), j = static_cast<int>((v / g.dims[0]) % g.dims[1]),
              k = static_cast<int>(v / (static_cast<std::size_t>(g.dims[0]) * g.dims[1]));
    const Eigen::Vector3d x = g.world_mm(i, j, k);
    fixed_v.push_back(intraop_t1.voxels[v]);
    warped_v.push_back(preop.linear(preop_t1.voxels, x + u.vectors[v].cast<double>(), 0.f));
    affine_v.push_back(preop.linear(preop_t1.voxels, (preop_from_intraop * x.homogeneous()).head<3>(), 0.f));
  }
  const double r2_warped = squared_correlation(fixed_v, warped_v), r2_affine = squared_correlation(fixed_v, affine_v);
  GateResult gate;
  gate.name = "image";
  gate.value = r2_warped - r2_affine;
  gate.limit = ">= " + fixed(-limits.image_r2_tolerance);
  gate.passed = gate.value >= -limits.image_r2_tolerance;
  gate.detail = "squared correlation of the warped preop T1 with the intraop image minus that of the affine alone";
  gate.extra = {{"r2_warped", r2_warped}, {"r2_affine", r2_affine}, {"samples", fixed_v.size()}};
  return gate;
}

}  // namespace brainshift
