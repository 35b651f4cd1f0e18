#pragma once
// report.png of one registration: the one place that turns a ScanResult (its
// images, metrics and kind) and the label table into the report's inputs,
// used by `brainshift register` and by the daemon.
#include <string>

#include "pipeline/engine_session.h"
#include "core/label_table.h"
#include "report/report.h"

namespace brainshift {

// The legend of the table (every entry, in table order, with its colour).
std::vector<ReportLegendEntry> report_legend(const LabelTable& table);

// The key numbers from result.metrics: "labels" / "labels_affine_only" (Dice,
// mean surface distance), "jacobian.min" and the largest "surfaces.*.
// max_residual_mm"; what the metrics lack stays absent ("n/a").
ReportSummary report_summary(const ScanResult& result, const std::string& scan_id);

// PNG bytes of the report; requires the quality metrics to have been added
// (warped_t1_affine_only is drawn in row 2). The slices pass through the
// first resectable structure (the tumour) when the table has one.
std::string scan_report_png(const ScanResult& result, const ImageF& intraop_t1, const LabelTable& table,
                            const std::string& scan_id);

}  // namespace brainshift
