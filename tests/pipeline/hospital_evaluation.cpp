#include "hospital_evaluation.h"

#include <algorithm>
#include <map>

#include "atlas/default_atlas.h"
#include "core/errors.h"
#include "field/metrics.h"
#include "image/distance_map.h"

namespace brainshift::evaluation {

AtlasInputs load_atlas_inputs(const std::string& atlas_cache, const std::string& templates_dir) {
  DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache, templates_dir);
  return {std::move(atlas.t1), std::move(atlas.labels)};
}

Subject make_named_subject(const AtlasInputs& atlas, const std::string& name, std::uint64_t seed_offset,
                           double cyst_radius_fraction) {
  for (auto s : hospital_subjects())
    if (s.name == name) {
      s.seed += seed_offset;
      if (s.tumor) {
        s.tumor->seed += seed_offset;
        s.tumor->cyst_radius_fraction = cyst_radius_fraction;
      }
      if (s.mass_effect) s.mass_effect->cyst_radius_fraction = cyst_radius_fraction;
      return make_subject(atlas.t1, atlas.labels, s);
    }
  throw InputError("no hospital subject named '" + name + "'");
}

const char* mode_name(InputMode m) {
  switch (m) {
    case InputMode::labels_and_image: return "labels+image";
    case InputMode::labels_only: return "labels";
    case InputMode::image_only: return "image";
  }
  return "?";
}

InputMode mode_from_name(const std::string& name) {
  for (InputMode m : {InputMode::labels_and_image, InputMode::labels_only, InputMode::image_only})
    if (name == mode_name(m)) return m;
  throw InputError("unknown mode '" + name + "' (labels+image, labels, image)");
}

nlohmann::json segmentation_agreement(const LabelImage& segmented, const LabelImage& truth,
                                      const std::vector<std::uint16_t>& ventricle_labels) {
  // Brain: the outline (everything labelled), as the outer surface uses it.
  std::size_t both = 0, a = 0, b = 0, vb = 0, va = 0, vt = 0;
  auto is_ventricle = [&](std::uint16_t l) {
    return std::find(ventricle_labels.begin(), ventricle_labels.end(), l) != ventricle_labels.end();
  };
  for (std::size_t v = 0; v < segmented.voxels.size() && v < truth.voxels.size(); ++v) {
    const bool x = segmented.voxels[v] != 0, y = truth.voxels[v] != 0;
    both += x && y;
    a += x;
    b += y;
    const bool p = is_ventricle(segmented.voxels[v]), q = is_ventricle(truth.voxels[v]);
    vb += p && q;
    va += p;
    vt += q;
  }
  const double voxel_ml = segmented.grid.spacing_mm().prod() / 1000.0;
  return {{"brain_dice", 2.0 * static_cast<double>(both) / static_cast<double>(std::max<std::size_t>(a + b, 1))},
          {"ventricle_dice", 2.0 * static_cast<double>(vb) / static_cast<double>(std::max<std::size_t>(va + vt, 1))},
          {"brain_ml",
           {{"segmented", voxel_ml * static_cast<double>(a)}, {"truth", voxel_ml * static_cast<double>(b)}}}};
}

nlohmann::json warped_beyond_truth(const LabelImage& warped, const LabelImage& truth) {
  const Mask brain = nonzero_mask(truth);
  const ImageF distance = distance_to_mask_mm(brain, 60.0);
  const double voxel_ml = truth.grid.spacing_mm().prod() / 1000.0;
  std::size_t beyond3 = 0, beyond6 = 0;
  double farthest = 0;
  for (std::size_t v = 0; v < warped.voxels.size() && v < truth.voxels.size(); ++v) {
    if (warped.voxels[v] == 0 || brain.voxels[v]) continue;
    const double d = distance.voxels[v];
    beyond3 += d > 3.0;
    beyond6 += d > 6.0;
    farthest = std::max(farthest, d);
  }
  return {{"beyond_3mm_ml", voxel_ml * static_cast<double>(beyond3)},
          {"beyond_6mm_ml", voxel_ml * static_cast<double>(beyond6)},
          {"farthest_mm", farthest}};
}

namespace {

// How near the brain-volume gate's bounds each round ran (change, bounds,
// kept), and the head placement's volume scale the gates take out.
nlohmann::json volume_gate_rounds(const nlohmann::json& segmentation_metrics) {
  const double scale = segmentation_metrics.contains("head_placement")
                           ? segmentation_metrics["head_placement"].value("volume_scale", 0.0)
                           : 0.0;  // refined given labels: no head placement
  nlohmann::json out = {{"placement_volume_scale", scale},
                        {"rounds", nlohmann::json::array()}};
  for (const auto& round : segmentation_metrics.value("rounds", nlohmann::json::array())) {
    const auto& v = round["gates"]["brain_volume"];
    if (v.is_null()) continue;
    out["rounds"].push_back({{"change", v["change"]}, {"allowed", v["allowed"]}, {"kept", round.value("kept", true)}});
  }
  return out;
}

}  // namespace

ModeRun run_mode(EngineSession& session, const HospitalCase& c, InputMode mode) {
  ModeRun run;
  run.mode = mode;
  ScanInput input;
  if (mode != InputMode::image_only) input.labels = c.phantom.intraop_labels;
  if (mode != InputMode::labels_only) input.image = c.phantom.intraop_t1;
  try {
    ScanResult result = session.register_scan(input, nullptr);
    if (result.intraop_labels) run.segmentation = segmentation_agreement(*result.intraop_labels, c.true_labels,
                                                session.parameters().label_table.cavity_labels());
    if (result.metrics.contains("segmentation") && result.metrics["segmentation"].contains("rounds"))
      run.segmentation["volume_gate"] = volume_gate_rounds(result.metrics["segmentation"]);
    if (result.metrics.contains("segmentation") && result.metrics["segmentation"].contains("enhanced_shell"))
      run.segmentation["enhanced_shell"] = result.metrics["segmentation"]["enhanced_shell"];
    run.caution = result_caution(result.metrics);
    if (result.metrics.contains("plausibility") && result.metrics["plausibility"].contains("affine_stretch")) {
      const auto& g = result.metrics["plausibility"]["affine_stretch"];
      run.affine_stretch = {{"value", g.value("value", 0.0)}, {"limit", g.value("limit", "")}};
      for (const auto& d : g.value("directions", nlohmann::json::array()))
        run.affine_stretch["brain_extent_in_view_mm"].push_back(d["brain_extent_in_view_mm"]);
    }
    if (result.metrics.contains("label_image_check")) run.label_image_check = result.metrics["label_image_check"];
    if (input.labels && input.image && result.metrics.contains("given_labels")) {
      const nlohmann::json& g = result.metrics["given_labels"];
      run.given_labels = {{"refined", g.value("refined", false)},
                          {"disregarded", g.value("disregarded", false)},
                          {"caution", result.metrics.value("caution", "")}};
      if (g.contains("changes")) run.given_labels["changes"] = g["changes"];
    }
    if (result.warped_labels.grid.same_geometry(c.true_labels.grid))
      run.warped_beyond_truth = warped_beyond_truth(result.warped_labels, c.true_labels);
    // The uncertainty map, after the answer as the daemon makes it.
    const IntraopInput prepared{result.labels_used(input.labels), input.image};
    session.add_uncertainty(prepared, result, nullptr);
    run.result = evaluate_result(c.phantom.description["name"].get<std::string>(), c.phantom, std::move(result));
  } catch (const InputError& e) {
    run.status = mode == InputMode::image_only ? ModeRun::Status::skipped : ModeRun::Status::error;
    run.note = mode == InputMode::image_only ? std::string("the image was refused: ") + e.what()
                                             : std::string("input error: ") + e.what();
  } catch (const std::exception& e) {
    run.status = ModeRun::Status::error;
    run.note = e.what();
  }
  return run;
}

namespace {

nlohmann::json mode_json(const ModeRun& r) {
  if (r.status == ModeRun::Status::skipped) return {{"status", "skipped"}, {"note", r.note}};
  if (r.status == ModeRun::Status::error) return {{"status", "error"}, {"note", r.note}};
  const CaseResult& c = r.result;
  return {{"status", "ran"},
          {"kind", c.fallback ? "affine_only_fallback" : "nonrigid"},
          {"fallback_reason", c.fallback_reason},
          {"tre_mm", {{"mean", c.nonrigid_mean_mm}, {"p95", c.nonrigid_p95_mm}, {"max", c.nonrigid_max_mm}}},
          {"tre_uncorrected_mm", {{"mean", c.uncorrected_mean_mm}, {"p95", c.uncorrected_p95_mm}}},
          {"tre_affine_mm", {{"mean", c.affine_mean_mm}, {"p95", c.affine_p95_mm}}},
          {"intraop_total_seconds", c.intraop_total_seconds},
          {"min_jacobian", c.metrics.contains("jacobian") ? c.metrics["jacobian"].value("min", 0.0) : 0.0},
          {"errors_mm", c.nonrigid_errors_mm},
          {"uncertainty_band_mm", c.predicted_band_mm},
          {"segmentation", r.segmentation},
          {"affine_stretch", r.affine_stretch},
          {"warped_beyond_truth", r.warped_beyond_truth},
          {"label_image_check", r.label_image_check},
          {"given_labels", r.given_labels},
          {"caution", r.caution}};
}

nlohmann::json brief(const nlohmann::json& d) {
  nlohmann::json b;
  for (const char* key : {"subject", "nonrigid_scale_applied", "min_jacobian", "landmarks", "sinking", "retractor",
                          "midline_shift", "resection", "swelling", "rigid"})
    if (d.contains(key)) b[key] = d[key];
  if (d.contains("scanner")) b["scanner"] = d["scanner"]["name"];
  if (d.contains("segmentation")) b["segmentation"] = d["segmentation"];
  if (d.contains("seconds")) b["generation_seconds"] = d["seconds"];
  return b;
}

}  // namespace

nlohmann::json case_record(const HospitalCaseSpec& spec, const HospitalCase& c, const std::vector<ModeRun>& runs) {
  nlohmann::json modes = nlohmann::json::object();
  for (const auto& r : runs) modes[mode_name(r.mode)] = mode_json(r);
  return {{"record", "case"}, {"case", spec.deformation.name}, {"subject", spec.subject},
          {"description", brief(c.description)}, {"modes", modes}};
}

nlohmann::json unfinished_case_record(const HospitalCaseSpec& spec, const std::string& why) {
  return {{"record", "case"}, {"case", spec.deformation.name}, {"subject", spec.subject},
          {"unfinished", why}, {"modes", nlohmann::json::object()}};
}

nlohmann::json summarise_records(const std::vector<nlohmann::json>& records, const std::vector<std::string>& modes) {
  struct Pool {
    int registrations = 0, nonrigid = 0, skipped = 0;
    double mean_sum = 0, worst = 0;
    double beyond_3mm_ml = 0, beyond_6mm_ml = 0, farthest_mm = 0;  // warped_beyond_truth, summed / largest
    int measured = 0;
    std::vector<double> errors, calibrated_errors, bands;  // bands: where the map was made
  };
  std::map<std::string, Pool> pools;
  std::vector<std::string> all_modes = modes;
  nlohmann::json cases = nlohmann::json::array(), preops = nlohmann::json::array();
  for (const auto& r : records)
    if (r.value("record", "") == "case")
      for (const auto& [mode, m] : r["modes"].items())
        if (std::find(all_modes.begin(), all_modes.end(), mode) == all_modes.end()) all_modes.push_back(mode);
  for (auto r : records) {
    const std::string kind = r.value("record", "");
    if (kind == "preop") {
      preops.push_back(r);
      continue;
    }
    if (kind != "case") continue;
    for (const auto& mode : all_modes) {
      Pool& p = pools[mode];
      if (r.contains("unfinished")) {
        ++p.registrations;  // a lost answer in every mode
        continue;
      }
      if (!r["modes"].contains(mode)) continue;
      nlohmann::json& m = r["modes"][mode];
      const std::string status = m.value("status", "");
      if (status == "skipped") {
        ++p.skipped;
        continue;
      }
      ++p.registrations;
      if (status != "ran") continue;
      p.nonrigid += m["kind"] == "nonrigid";
      p.mean_sum += m["tre_mm"]["mean"].get<double>();
      p.worst = std::max(p.worst, m["tre_mm"]["max"].get<double>());
      if (m.contains("warped_beyond_truth") && m["warped_beyond_truth"].is_object()) {
        const auto& w = m["warped_beyond_truth"];
        p.beyond_3mm_ml += w.value("beyond_3mm_ml", 0.0);
        p.beyond_6mm_ml += w.value("beyond_6mm_ml", 0.0);
        p.farthest_mm = std::max(p.farthest_mm, w.value("farthest_mm", 0.0));
      }
      ++p.measured;
      for (const auto& e : m["errors_mm"]) p.errors.push_back(e.get<double>());
      if (m.contains("uncertainty_band_mm") && m["uncertainty_band_mm"].size() == m["errors_mm"].size()) {
        for (const auto& e : m["errors_mm"]) p.calibrated_errors.push_back(e.get<double>());
        for (const auto& b : m["uncertainty_band_mm"]) p.bands.push_back(b.get<double>());
        m["uncertainty_calibration"] = to_json(calibrate(m["uncertainty_band_mm"].get<std::vector<double>>(),
                                                         m["errors_mm"].get<std::vector<double>>()));
      }
      m.erase("errors_mm");
      m.erase("uncertainty_band_mm");
    }
    cases.push_back(r);
  }
  nlohmann::json summary = nlohmann::json::object();
  for (const auto& [mode, p] : pools)
    summary[mode] = {{"registrations", p.registrations},
                     {"skipped", p.skipped},
                     {"nonrigid_fraction", p.registrations ? static_cast<double>(p.nonrigid) / p.registrations : 0.0},
                     {"tre_mean_over_cases_mm", p.measured ? p.mean_sum / p.measured : 0.0},
                     {"tre_pooled_p95_mm", p.errors.empty() ? 0.0 : percentile(p.errors, 95.0)},
                     {"tre_worst_landmark_mm", p.worst},
                     {"cases_measured", p.measured},
                     {"warped_beyond_truth", {{"beyond_3mm_ml_summed", p.beyond_3mm_ml},
                                              {"beyond_6mm_ml_summed", p.beyond_6mm_ml},
                                              {"farthest_mm", p.farthest_mm}}},
                     {"uncertainty_calibration", to_json(calibrate(p.bands, p.calibrated_errors))}};
  return {{"summary", summary}, {"preops", preops}, {"cases", cases}};
}

}  // namespace brainshift::evaluation
