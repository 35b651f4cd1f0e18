#pragma once
// Runs registrations on synthetic brain-shift cases with a known truth and
// measures target registration error (TRE) at the phantom's landmarks:
// uncorrected (identity), affine only, and the full non-rigid result.
// Shared by the accuracy test and the pipeline benchmark.
#include <nlohmann/json.hpp>
#include <vector>

#include "phantom/brain_shift_phantom.h"
#include "pipeline/engine_session.h"

namespace brainshift::evaluation {

struct CaseResult {
  std::string name;
  double uncorrected_mean_mm = 0, uncorrected_p95_mm = 0;
  double affine_mean_mm = 0, affine_p95_mm = 0;
  double nonrigid_mean_mm = 0, nonrigid_p95_mm = 0, nonrigid_max_mm = 0;
  double max_true_displacement_mm = 0;
  double intraop_total_seconds = 0;
  bool fallback = false;
  std::string fallback_reason;  // when fallback
  std::vector<double> nonrigid_errors_mm;  // per landmark
  // The uncertainty map's 95 % band at each landmark (empty without the map).
  std::vector<double> predicted_band_mm;
  // Per landmark, with the map: what the error might depend on (for the
  // calibration study; landmark_records()).
  nlohmann::json landmark_records = nlohmann::json::array();
  nlohmann::json timings, metrics;
};

// One case: make the phantom from the session's preop, register, measure.
CaseResult evaluate_case(EngineSession& session, const PhantomSpec& spec);

// Measures one registration of a case made elsewhere (e.g. a robustness case).
CaseResult evaluate_result(const std::string& name, const PhantomCase& c, const ScanResult& r);

nlohmann::json to_json(const CaseResult& r);

// Pools the landmark errors of several cases.
struct Summary {
  double mean_mm = 0;                  // mean over cases of the per-case mean
  double p95_mm = 0;                   // worst per-case p95
  double pooled_p95_mm = 0;            // p95 over every landmark of every case
  double removed_fraction = 0, affine_mean_mm = 0, uncorrected_mean_mm = 0;
};
Summary summarise(const std::vector<CaseResult>& cases);

// How well the uncertainty map predicts the landmark errors, pooled over
// every landmark of the cases that have a map.
struct Calibration {
  std::size_t landmarks = 0;
  double spearman = 0;        // rank correlation of predicted band and actual error
  double coverage = 0;        // fraction of landmarks whose error is inside the band
  double width_ratio = 0;     // mean band / mean actual error
  double mean_band_mm = 0, mean_error_mm = 0;
};
Calibration calibrate(const std::vector<CaseResult>& cases);
// The same from pooled per-landmark bands and errors (equal sizes).
Calibration calibrate(const std::vector<double>& band, const std::vector<double>& error);
nlohmann::json to_json(const Calibration& c);

// Spearman rank correlation (ties take their mean rank); 0 when either is constant.
double spearman(const std::vector<double>& a, const std::vector<double>& b);

}  // namespace brainshift::evaluation
