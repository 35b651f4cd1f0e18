#include "pipeline/scan_report.h"

namespace brainshift {
namespace {

std::optional<double> number_at(const nlohmann::json& j, const char* a, const char* b) {
  if (!j.is_object() || !j.contains(a) || !j[a].is_object() || !j[a].contains(b) || !j[a][b].is_number())
    return std::nullopt;
  return j[a][b].get<double>();
}

}  // namespace

std::vector<ReportLegendEntry> report_legend(const LabelTable& table) {
  std::vector<ReportLegendEntry> legend;
  for (const auto& e : table.entries) legend.push_back({e.value, e.name, e.colour});
  return legend;
}

ReportSummary report_summary(const ScanResult& result, const std::string& scan_id) {
  ReportSummary s;
  s.scan_id = scan_id;
  s.fallback = result.kind == ResultKind::affine_only_fallback;
  s.fallback_reason = result.fallback_reason;
  const nlohmann::json& m = result.metrics;
  s.caution = result_caution(m);
  if (m.contains("labels") && m["labels"].is_object()) {
    const nlohmann::json none = nlohmann::json::object();
    const nlohmann::json& before = m.contains("labels_affine_only") ? m["labels_affine_only"] : none;
    for (const auto& [name, after] : m["labels"].items()) {
      ReportSummary::Overlap o;
      o.structure = name;
      o.dice = number_at(m["labels"], name.c_str(), "dice");
      o.mean_distance_mm = number_at(m["labels"], name.c_str(), "mean_surface_distance_mm");
      o.dice_affine = number_at(before, name.c_str(), "dice");
      o.mean_distance_affine_mm = number_at(before, name.c_str(), "mean_surface_distance_mm");
      s.overlaps.push_back(o);
    }
  }
  s.min_jacobian = number_at(m, "jacobian", "min");
  if (m.contains("plausibility")) s.brain_in_view_fraction = number_at(m["plausibility"], "volume", "preop_fraction_in_view");
  if (m.contains("uncertainty")) {
    s.uncertainty_median_mm = number_at(m["uncertainty"], "band95_mm", "median");
    s.uncertainty_p95_mm = number_at(m["uncertainty"], "band95_mm", "p95");
  }
  if (m.contains("surfaces") && m["surfaces"].is_object())
    for (const auto& [name, surface] : m["surfaces"].items()) {
      const auto r = number_at(m["surfaces"], name.c_str(), "max_residual_mm");
      if (r && (!s.worst_residual_mm || *r > *s.worst_residual_mm)) {
        s.worst_residual_mm = r;
        s.worst_residual_surface = name;
      }
    }
  return s;
}

std::string scan_report_png(const ScanResult& r, const ImageF& intraop_t1, const LabelTable& table,
                            const std::string& scan_id) {
  ReportInputs in;
  in.intraop = &intraop_t1;
  in.warped_preop_affine = &r.warped_t1_affine_only;
  in.warped_preop_nonrigid = &r.warped_t1;
  in.warped_labels = &r.warped_labels;
  in.legend = report_legend(table);
  in.outer_label = table.brain_label();
  in.summary = report_summary(r, scan_id);
  if (r.intraop_labels) in.segmentation = &*r.intraop_labels;
  if (!r.uncertainty_mm.voxels.empty()) in.uncertainty_mm = &r.uncertainty_mm;
  ReportOptions options;
  if (const auto resectable = table.resectable_labels(); !resectable.empty()) options.centre_label = resectable.front();
  return report_png_bytes(in, options);
}

}  // namespace brainshift
