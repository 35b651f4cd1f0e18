#include "phantom_evaluation.h"

#include <algorithm>

#include "core/timer.h"
#include "field/metrics.h"

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

}  // namespace brainshift::evaluation
