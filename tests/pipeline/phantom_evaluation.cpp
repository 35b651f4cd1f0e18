#include "phantom_evaluation.h"

#include <algorithm>
#include <cmath>

#include "atlas/default_atlas.h"
#include "core/timer.h"
#include "field/vector_sampling.h"
#include "image/distance_map.h"
#include "field/metrics.h"
#include "image/resample.h"

namespace brainshift::evaluation {
namespace {

struct Errors {
  std::vector<double> uncorrected, affine, nonrigid;
};

Errors landmark_errors(const PhantomCase& c, const ScanResult& r) {
  std::vector<Eigen::Vector3d> x, p;
  for (const auto& [xi, pi] : c.landmarks_intraop_preop_mm) {
    x.push_back(xi);
    p.push_back(pi);
  }
  Errors e;
  const Eigen::Matrix4d preop_from_intraop = r.intraop_from_preop.inverse();
  for (std::size_t i = 0; i < x.size(); ++i) {
    e.uncorrected.push_back((x[i] - p[i]).norm());
    e.affine.push_back(((preop_from_intraop * x[i].homogeneous()).head<3>() - p[i]).norm());
  }
  e.nonrigid = target_registration_error(r.pullback_field_mm, x, p).errors_mm;
  return e;
}

double mean(const std::vector<double>& v) {
  double s = 0;
  for (double d : v) s += d;
  return v.empty() ? 0 : s / static_cast<double>(v.size());
}

// Per landmark: its error and predicted band, and the local quantities the
// error might depend on (distance from the boundary data, displacement, its
// gradient), for the calibration study.
nlohmann::json landmark_records(const PhantomCase& c, const ScanResult& r, const std::vector<double>& errors,
                                const std::vector<double>& band) {
  const LabelImage& labels = c.intraop_labels;
  Mask outside(labels.grid), ventricles(labels.grid);
  for (std::size_t v = 0; v < labels.voxels.size(); ++v) {
    outside.voxels[v] = labels.voxels[v] == 0;
    ventricles.voxels[v] = labels.voxels[v] == atlas_labels::ventricles;
  }
  const ImageF depth = distance_to_mask_mm(outside), to_ventricles = distance_to_mask_mm(ventricles);
  const GridSampler at(labels.grid);
  const Eigen::Matrix4d preop_from_intraop = r.intraop_from_preop.inverse();
  nlohmann::json out = nlohmann::json::array();
  std::size_t i = 0;
  for (const auto& [x, p] : c.landmarks_intraop_preop_mm) {
    const auto u = sample_vector_linear(r.pullback_field_mm, x);
    const Eigen::Vector3d affine = (preop_from_intraop * x.homogeneous()).head<3>();
    double grad = 0;
    for (int a = 0; a < 3; ++a) {
      Eigen::Vector3d h = Eigen::Vector3d::Zero();
      h[a] = 1.5;
      const auto up = sample_vector_linear(r.pullback_field_mm, x + h), um = sample_vector_linear(r.pullback_field_mm, x - h);
      if (up && um) grad += ((*up - *um) / 3.0).squaredNorm();
    }
    const Eigen::Vector3d q = u ? Eigen::Vector3d(x + *u) : affine;
    out.push_back({{"error", errors[i]}, {"band", i < band.size() ? band[i] : 0.0},
                   {"depth", at.linear(depth.voxels, x, 0.f)}, {"ventricle", at.linear(to_ventricles.voxels, x, 0.f)},
                   {"pred_nonrigid", (q - affine).norm()}, {"true_nonrigid", (p - affine).norm()},
                   {"grad_u", std::sqrt(grad)}, {"pred", {q[0], q[1], q[2]}}, {"x", {x[0], x[1], x[2]}}});
    ++i;
  }
  return out;
}

}  // namespace

CaseResult evaluate_case(EngineSession& session, const PhantomSpec& spec) {
  const PhantomCase c = make_phantom(session.preop().t1, session.preop().labels, spec);
  IntraopInput input{c.intraop_labels, c.intraop_t1};
  return evaluate_result(spec.name, c, session.register_scan(input, nullptr));
}

CaseResult evaluate_result(const std::string& name, const PhantomCase& c, const ScanResult& r) {
  const Errors e = landmark_errors(c, r);
  CaseResult out;
  out.name = name;
  out.uncorrected_mean_mm = mean(e.uncorrected);
  out.uncorrected_p95_mm = percentile(e.uncorrected, 95.0);
  out.affine_mean_mm = mean(e.affine);
  out.affine_p95_mm = percentile(e.affine, 95.0);
  out.nonrigid_mean_mm = mean(e.nonrigid);
  out.nonrigid_p95_mm = percentile(e.nonrigid, 95.0);
  out.nonrigid_max_mm = *std::max_element(e.nonrigid.begin(), e.nonrigid.end());
  out.max_true_displacement_mm = *std::max_element(e.uncorrected.begin(), e.uncorrected.end());
  out.intraop_total_seconds = r.timings["intraop"]["total"].get<double>();
  out.fallback = r.kind != ResultKind::nonrigid;
  out.fallback_reason = r.fallback_reason;
  out.nonrigid_errors_mm = e.nonrigid;
  if (!r.uncertainty_mm.voxels.empty()) {
    const GridSampler map(r.uncertainty_mm.grid);
    for (const auto& [x, p] : c.landmarks_intraop_preop_mm)
      out.predicted_band_mm.push_back(map.linear(r.uncertainty_mm.voxels, x, 0.f));
    out.landmark_records = landmark_records(c, r, e.nonrigid, out.predicted_band_mm);
  }
  out.timings = r.timings;
  out.metrics = r.metrics;
  return out;
}

nlohmann::json to_json(const CaseResult& r) {
  return {{"case", r.name},
          {"tre_uncorrected_mm", {{"mean", r.uncorrected_mean_mm}, {"p95", r.uncorrected_p95_mm}}},
          {"tre_affine_mm", {{"mean", r.affine_mean_mm}, {"p95", r.affine_p95_mm}}},
          {"tre_nonrigid_mm", {{"mean", r.nonrigid_mean_mm}, {"p95", r.nonrigid_p95_mm}, {"max", r.nonrigid_max_mm}}},
          {"max_landmark_displacement_mm", r.max_true_displacement_mm},
          {"fallback", r.fallback},
          {"fallback_reason", r.fallback_reason},
          {"timings", r.timings},
          {"metrics", r.metrics}};
}

Summary summarise(const std::vector<CaseResult>& cases) {
  Summary s;
  double n = 0;
  std::vector<double> pooled;
  for (const auto& c : cases) {
    pooled.insert(pooled.end(), c.nonrigid_errors_mm.begin(), c.nonrigid_errors_mm.end());
    s.mean_mm += c.nonrigid_mean_mm;
    s.p95_mm = std::max(s.p95_mm, c.nonrigid_p95_mm);
    s.affine_mean_mm += c.affine_mean_mm;
    s.uncorrected_mean_mm += c.uncorrected_mean_mm;
    n += 1;
  }
  if (n > 0) {
    s.mean_mm /= n;
    s.affine_mean_mm /= n;
    s.uncorrected_mean_mm /= n;
  }
  if (!pooled.empty()) s.pooled_p95_mm = percentile(pooled, 95.0);
  s.removed_fraction = s.uncorrected_mean_mm > 0 ? 1.0 - s.mean_mm / s.uncorrected_mean_mm : 0.0;
  return s;
}

namespace {

std::vector<double> ranks(const std::vector<double>& v) {
  std::vector<std::size_t> order(v.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return v[a] < v[b]; });
  std::vector<double> r(v.size());
  for (std::size_t i = 0; i < order.size();) {
    std::size_t j = i;
    while (j + 1 < order.size() && v[order[j + 1]] == v[order[i]]) ++j;
    for (std::size_t k = i; k <= j; ++k) r[order[k]] = 0.5 * static_cast<double>(i + j);
    i = j + 1;
  }
  return r;
}

}  // namespace

double spearman(const std::vector<double>& a, const std::vector<double>& b) {
  const std::vector<double> ra = ranks(a), rb = ranks(b);
  const double n = static_cast<double>(std::min(ra.size(), rb.size()));
  if (n < 3) return 0;
  double ma = 0, mb = 0;
  for (std::size_t i = 0; i < n; ++i) ma += ra[i] / n, mb += rb[i] / n;
  double sab = 0, saa = 0, sbb = 0;
  for (std::size_t i = 0; i < n; ++i) {
    sab += (ra[i] - ma) * (rb[i] - mb);
    saa += (ra[i] - ma) * (ra[i] - ma);
    sbb += (rb[i] - mb) * (rb[i] - mb);
  }
  return saa > 0 && sbb > 0 ? sab / std::sqrt(saa * sbb) : 0.0;
}

Calibration calibrate(const std::vector<CaseResult>& cases) {
  std::vector<double> band, error;
  for (const auto& c : cases) {
    if (c.predicted_band_mm.size() != c.nonrigid_errors_mm.size()) continue;
    band.insert(band.end(), c.predicted_band_mm.begin(), c.predicted_band_mm.end());
    error.insert(error.end(), c.nonrigid_errors_mm.begin(), c.nonrigid_errors_mm.end());
  }
  return calibrate(band, error);
}

Calibration calibrate(const std::vector<double>& band, const std::vector<double>& error) {
  Calibration out;
  out.landmarks = band.size();
  if (band.empty() || band.size() != error.size()) return out;
  std::size_t inside = 0;
  for (std::size_t i = 0; i < band.size(); ++i) {
    inside += error[i] <= band[i];
    out.mean_band_mm += band[i] / static_cast<double>(band.size());
    out.mean_error_mm += error[i] / static_cast<double>(band.size());
  }
  out.spearman = spearman(band, error);
  out.coverage = static_cast<double>(inside) / static_cast<double>(band.size());
  out.width_ratio = out.mean_error_mm > 0 ? out.mean_band_mm / out.mean_error_mm : 0.0;
  return out;
}

nlohmann::json to_json(const Calibration& c) {
  return {{"landmarks", c.landmarks}, {"spearman", c.spearman}, {"coverage_95", c.coverage},
          {"width_ratio", c.width_ratio}, {"mean_band_mm", c.mean_band_mm}, {"mean_error_mm", c.mean_error_mm}};
}

}  // namespace brainshift::evaluation
