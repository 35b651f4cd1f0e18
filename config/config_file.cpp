#include "config_file.h"

#include "config/toml_reader.h"
#include "core/errors.h"
#include "core/file_bytes.h"
#include "embedded_defaults.h"

namespace brainshift::config {
namespace {

void read_mesh(TomlSection& root, MeshingParameters& p) {
  TomlSection s = root.table("mesh");
  s.read("facet_angle_deg", p.facet_angle_deg);
  s.read("facet_size_mm", p.facet_size_mm);
  s.read("facet_distance_mm", p.facet_distance_mm);
  s.read("cell_size_mm", p.cell_size_mm);
  s.read("cell_radius_edge_ratio", p.cell_radius_edge_ratio);
  s.read("optimise", p.optimise);
  s.read("random_seed", p.random_seed);
  s.reject_unknown_keys();
}

SolverKind solver_from(const TomlSection& s, const std::string& name) {
  if (name == "direct") return SolverKind::direct_cholesky;
  if (name == "cg_gamg") return SolverKind::cg_gamg;
  if (name == "gmres_bjacobi") return SolverKind::gmres_bjacobi;
  s.fail("solver", "\"" + name + "\" is not one of direct, cg_gamg, gmres_bjacobi");
}

DirichletMethod dirichlet_from(const TomlSection& s, const std::string& name) {
  if (name == "symmetric_elimination") return DirichletMethod::symmetric_elimination;
  if (name == "row_replacement") return DirichletMethod::row_replacement;
  s.fail("dirichlet", "\"" + name + "\" is not symmetric_elimination or row_replacement");
}

void read_elastic(TomlSection& root, ElasticOptions& p) {
  TomlSection s = root.table("elastic");
  p.solver = solver_from(s, s.string("solver", "direct"));
  p.dirichlet = dirichlet_from(s, s.string("dirichlet", "symmetric_elimination"));
  s.read("direct_package", p.direct_package);
  s.read("rtol", p.rtol);
  s.read("max_iterations", p.max_iterations);
  s.read("petsc_options", p.petsc_options);
  s.reject_unknown_keys();
  if (p.direct_package != "cholmod" && p.direct_package != "mumps")
    s.fail("direct_package", "must be cholmod or mumps");
}

void read_affine(TomlSection& root, AffineRegistrationParameters& p) {
  TomlSection s = root.table("affine");
  s.read("levels", p.levels);
  s.read("coarse_points", p.coarse_points);
  s.read("fine_points", p.fine_points);
  s.read("iterations_per_level", p.iterations_per_level);
  s.read("robust_scale_mm", p.robust_scale_mm);
  s.read("coarse_scale_factor", p.coarse_scale_factor);
  s.read("brain_weight", p.brain_weight);
  s.read("ventricle_weight", p.ventricle_weight);
  s.read("tolerance_mm", p.tolerance_mm);
  s.read("coarse_tolerance_mm", p.coarse_tolerance_mm);
  s.read("min_inlier_fraction", p.min_inlier_fraction);
  s.read("data_scale_factor", p.data_scale_factor);
  s.read("min_robust_scale_mm", p.min_robust_scale_mm);
  s.read("max_affine_sigma_ratio", p.max_affine_sigma_ratio, Interval::closed(0, 1));
  s.reject_unknown_keys();
}

void read_surface(TomlSection& surface, const char* which, ActiveSurfaceParameters& p,
                  double* min_cavity_ml = nullptr) {
  TomlSection s = surface.table(which);
  if (min_cavity_ml) s.read("min_cavity_ml", *min_cavity_ml, Interval::above(0));
  s.read("max_iterations", p.max_iterations);
  s.read("step", p.step);
  s.read("membrane_stiffness", p.membrane_stiffness);
  s.read("convergence_tolerance_mm", p.convergence_tolerance_mm);
  s.read("convergence_iterations", p.convergence_iterations);
  s.read("max_step_mm", p.max_step_mm);
  s.read("force_smoothing_mm", p.force_smoothing_mm);
  s.read("edge_weight", p.edge_weight);
  s.read("edge_search_mm", p.edge_search_mm);
  s.read("contact_fraction", p.contact_fraction, Interval::open(0, 1));
  s.read("capture_range_mm", p.capture_range_mm, Interval::at_least(0));  // 0: unlimited
  s.read("stiffness_levels", p.stiffness_levels, 1, 8);
  s.read("normal_search_mm", p.normal_search_mm, Interval::closed(0, 50));
  s.read("stiffness_ratio", p.stiffness_ratio, Interval::at_least(1));
  s.read("fold_guard", p.fold_guard_enabled);
  s.read("max_normal_turn_deg", p.fold_guard.max_normal_turn_deg, Interval::open(0, 90));
  s.read("min_area_ratio", p.fold_guard.min_area_ratio, Interval::open(0, 1));
  s.reject_unknown_keys();
}

void read_surface_repair(TomlSection& surface, SurfaceRepairParameters& p) {
  TomlSection s = surface.table("repair");
  s.read("enabled", p.enabled);
  s.read("unreliable_residual_mm", p.unreliable_residual_mm, Interval::above(0));
  s.read("rounds", p.rounds, 1, 50);
  s.read("min_component_area_mm2", p.min_component_area_mm2, Interval::at_least(0));
  s.read("smoothing_mm", p.smoothing_mm, Interval::above(0));
  s.read("max_search_mm", p.max_search_mm);
  s.reject_unknown_keys();
  if (!(p.max_search_mm >= 3 * p.smoothing_mm)) s.fail("max_search_mm", "must be >= 3 x smoothing_mm");
}

void read_surfaces(TomlSection& root, PipelineParameters& p) {
  TomlSection surface = root.table("surface");
  read_surface(surface, "outer", p.outer_surface);
  read_surface(surface, "ventricles", p.ventricle_surface);
  read_surface(surface, "resection", p.resection_surface, &p.min_resection_cavity_ml);
  read_surface_repair(surface, p.surface_repair);
  surface.reject_unknown_keys();
}

// Ranges are the engine's (validation_error names the key); checked here too
// so a bad value is refused when the file is read, not at the first scan.
void read_intensity(TomlSection& root, IntensityRefinementParameters& p) {
  TomlSection s = root.table("intensity");
  s.read("enabled", p.enabled);
  s.read("lattice_spacing_mm", p.lattice_spacing_mm);
  s.read("iterations", p.iterations);
  s.read("convergence_mm", p.convergence_mm);
  s.read("membrane_weight", p.membrane_weight);
  s.read("shrink_weight_per_mm2", p.shrink_weight_per_mm2);
  s.read("smoothing_length_mm", p.smoothing_length_mm);
  s.read("fem_trust_length_mm", p.fem_trust_length_mm);
  s.read("match_point_spread", p.match_point_spread);
  s.read("max_correction_mm", p.max_correction_mm);
  s.read("max_step_mm", p.max_step_mm);
  s.read("sample_spacing_mm", p.sample_spacing_mm);
  s.read("max_samples", p.max_samples);
  s.read("boundary_margin_mm", p.boundary_margin_mm);
  s.read("robust_scale", p.robust_scale);
  s.read("bias_degree", p.bias_degree);
  s.read("outside_fade_mm", p.outside_fade_mm);
  s.read("min_explained_variance", p.min_explained_variance);
  s.reject_unknown_keys();
  const std::string error = validation_error(p);
  if (!error.empty()) s.fail(error);
}

// [auto_segmentation]: a scan pushed as an image alone (DESIGN.md
// "Automatic intraop segmentation" says why each default). The classifier's
// settings serve both the image-only path and the check of given labels
// against their image; the prior widths are each path's own.
void read_classifier(TomlSection& s, segmentation::SegmentationParameters& c) {
  s.read("prior_floor", c.prior_floor, Interval::open(0, 0.5));
  s.read("margin_mm", c.margin_mm, Interval::at_least(0));
  s.read("min_fluid_contrast_sd", c.min_fluid_contrast_sd, Interval::above(0));
  s.read("max_sulcus_half_width_mm", c.max_sulcus_half_width_mm, Interval::at_least(0));
  s.read("max_cap_mm", c.max_cap_mm, Interval::at_least(0));
  s.read("min_gap_ml", c.min_gap_ml, Interval::at_least(0));
  s.read("max_gap_median_toward_fluid_turn", c.max_gap_median_toward_fluid_turn, Interval::above(0));
  s.read("min_gap_preop_toward_tissue", c.min_gap_preop_toward_tissue, Interval::closed(0, 1));
  s.read("max_fluid_rim_mm", c.max_fluid_rim_mm, Interval::closed(0, 10));
  s.read("max_rim_cap_mm", c.max_rim_cap_mm, Interval::closed(0, 10));
  s.read("rim_cap_cavity_margin_mm", c.rim_cap_cavity_margin_mm, Interval::closed(0, 50));
  s.read("bias_degree", c.em.bias_degree, 0, 4);
  s.read("sharpening_bias", c.sharpening_bias);
  s.read("sharpening_smoothing_mm", c.sharpening.smoothing_mm, Interval::closed(5, 200));
  s.read("sharpening_max_iterations", c.sharpening.max_iterations, 1, 1000);
  s.read("max_iterations", c.em.max_iterations, 1, 1000);
  s.read("tolerance", c.em.tolerance, Interval::above(0));
  s.read("fit_samples", c.em.fit_samples, 1000, 100000000);
  s.read("mrf_beta", c.em.mrf_beta, Interval::closed(0, 10));
  s.read("mrf_sweeps", c.em.mrf_sweeps, 0, 100);
  s.reject_unknown_keys();
}

void read_auto_segmentation(TomlSection& root, AutoSegmentationParameters& p) {
  TomlSection s = root.table("auto_segmentation");
  s.read("prior_width_affine_mm", p.prior_width_affine_mm, Interval::above(0));
  s.read("prior_width_nonrigid_mm", p.prior_width_nonrigid_mm, Interval::above(0));
  s.read("prior_inward_width_affine_mm", p.prior_inward_width_affine_mm, Interval::above(0));
  s.read("prior_inward_width_nonrigid_mm", p.prior_inward_width_nonrigid_mm, Interval::above(0));
  s.read("ventricle_shift_affine_mm", p.ventricle_shift_affine_mm, Interval::closed(0, 30));
  s.read("ventricle_prior_width_mm", p.ventricle_prior_width_mm, Interval::above(0));
  s.read("bright_fluid_bias_degree_affine", p.bright_fluid_bias_degree_affine, 0, 4);
  s.read("working_spacing_mm", p.working_spacing_mm, Interval::closed(0, 3));
  s.read("rematch_rounds", p.rematch_rounds, 0, 5);
  s.read("rematch_reuses_fit", p.rematch_reuses_fit);
  s.read("rematch_gaps_found_before", p.rematch_gaps_found_before);
  s.read("max_brain_volume_change", p.max_brain_volume_change, Interval::open(0, 1));
  s.read("min_ventricle_fraction", p.min_ventricle_fraction, Interval::closed(0, 1));
  s.read("min_surface_confidence", p.min_surface_confidence, Interval::closed(0, 1));
  s.read("max_uncertain_surface_fraction", p.max_uncertain_surface_fraction, Interval::closed(0, 1));
  s.read("check_given_labels", p.check_given_labels);
  const std::string use = s.string("given_labels", std::string(to_string(p.given_labels)));
  if (auto u = given_labels_use_from_string(use)) p.given_labels = *u;
  else s.fail("given_labels", "\"" + use + "\" is not refine or exact");
  TomlSection classifier = s.table("classifier");
  read_classifier(classifier, p.classifier);
  TomlSection check = s.table("label_check");
  auto& c = p.label_image_check;
  c.classifier = p.classifier;  // one classifier; the check sets its own prior width
  check.read("prior_width_mm", c.prior_width_mm, Interval::above(0));
  check.read("min_posterior", c.min_posterior, Interval::open(0.5, 1));
  check.read("band_mm", c.band_mm, Interval::at_least(0));
  check.read("max_disagreement_fraction", c.max_disagreement_fraction, Interval::open(0, 1));
  check.reject_unknown_keys();
  TomlSection passes = s.table("passes");
  passes.read("prior_refine", p.passes.prior_refine);
  passes.read("prior_surface_max_iterations", p.passes.prior_surface_max_iterations, 0, 1000);
  passes.read("warm_start_affine", p.passes.warm_start_affine);
  passes.read("prior_spacing_mm", p.passes.prior_spacing_mm, Interval::at_least(0));
  passes.read("stage_spacing_mm", p.passes.stage_spacing_mm, Interval::at_least(0));
  passes.reject_unknown_keys();
  s.reject_unknown_keys();
}

void read_rest(TomlSection& root, PipelineParameters& p) {
  TomlSection field = root.table("field");
  field.read("blend_distance_mm", p.field.blend_distance_mm);
  field.read("barycentric_tolerance", p.field.barycentric_tolerance);
  field.read("smoothing_sweeps", p.field.smoothing_sweeps);
  field.reject_unknown_keys();
  TomlSection models = root.table("models");
  models.read("presmooth_sigma_mm", p.models.presmooth_sigma_mm);
  models.read("taubin_iterations", p.models.taubin_iterations);
  models.read("taubin_lambda", p.models.taubin_lambda);
  models.read("taubin_mu", p.models.taubin_mu);
  models.reject_unknown_keys();
  TomlSection gates = root.table("gates");
  gates.read("min_jacobian_determinant", p.gates.min_jacobian_determinant);
  gates.read("max_mean_surface_residual_mm", p.gates.max_mean_surface_residual_mm);
  gates.read("min_intraop_brain_fraction", p.gates.min_intraop_brain_fraction);
  gates.read("max_unsupported_displacement_mm", p.gates.max_unsupported_displacement_mm, Interval::above(0));
  gates.reject_unknown_keys();
  TomlSection limits = root.table("limits");
  limits.read("max_image_bytes", p.max_image_bytes);
  limits.reject_unknown_keys();
}

// label_table = "labels.toml": the table in a file of its own, relative to
// the configuration file (or the built-in one when read from text).
LabelTable label_table_file(TomlSection& root, const std::string& path, const std::filesystem::path* base_dir) {
  if (base_dir) {
    const auto full = std::filesystem::path(path).is_absolute() ? std::filesystem::path(path) : *base_dir / path;
    return label_table_from_text(read_whole_file(full, "label table"), full.string());
  }
  if (path == "labels.toml") return default_label_table();
  root.fail("label_table", "\"" + path + "\" cannot be resolved without a file location");
}

PipelineParameters parameters_from(const toml::table& document, const std::string& src,
                                   const std::filesystem::path* base_dir) {
  TomlSection root(&document, src, "");
  root.allow({"server", "security", "openigtlink", "dicom_node"});  // brainshiftd's (server/server_settings.cpp) and brainshift-dicom-node's (server/dicom_node.cpp)
  PipelineParameters p;
  const std::string label_table = root.string("label_table", "");
  if (root.node("label")) p.label_table = label_table_from_document(root);
  else if (!label_table.empty()) p.label_table = label_table_file(root, label_table, base_dir);
  else p.label_table = default_label_table();
  read_mesh(root, p.meshing);
  read_elastic(root, p.elastic);
  read_affine(root, p.affine);
  read_surfaces(root, p);
  read_intensity(root, p.intensity);
  read_auto_segmentation(root, p.auto_segmentation);
  read_rest(root, p);
  root.reject_unknown_keys("unknown top-level key or section");
  return p;
}

}  // namespace

const std::string& default_config_text() { return embedded_brainshiftd_toml(); }

PipelineParameters pipeline_parameters_from_file(const std::filesystem::path& path) {
  const std::string src = path.string();
  const auto base = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  return parameters_from(parse_toml(read_whole_file(path, "configuration file"), src), src, &base);
}

PipelineParameters pipeline_parameters_from_text(const std::string& toml_text, const std::string& source_name) {
  return parameters_from(parse_toml(toml_text, source_name), source_name, nullptr);
}

}  // namespace brainshift::config
