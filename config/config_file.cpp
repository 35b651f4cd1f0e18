#include "config_file.h"

#include <fstream>
#include <set>
#include <sstream>

#include <toml++/toml.h>

#include "core/errors.h"
#include "embedded_defaults.h"

namespace brainshift::config {
namespace {

// Reads keys of one TOML table into struct fields and remembers which keys were
// known, so that leftovers (typos) can be reported.
class Section {
 public:
  Section(const toml::table* table, std::string name, std::string source)
      : table_(table), name_(std::move(name)), source_(std::move(source)) {}

  template <class T>
  void read(const char* key, T& field) {
    known_.insert(key);
    if (!table_) return;
    const toml::node* node = table_->get(key);
    if (!node) return;
    if constexpr (std::is_same_v<T, bool>) {
      if (auto v = node->value<bool>()) { field = *v; return; }
    } else if constexpr (std::is_integral_v<T>) {
      if (auto v = node->value<std::int64_t>()) {
        if (*v < 0 && std::is_unsigned_v<T>) fail(key, "must not be negative");
        field = static_cast<T>(*v);
        return;
      }
    } else if constexpr (std::is_floating_point_v<T>) {
      if (auto v = node->value<double>()) { field = static_cast<T>(*v); return; }
    } else {
      if (auto v = node->value<std::string>()) { field = *v; return; }
    }
    fail(key, "has the wrong type");
  }

  void finish() const {
    if (!table_) return;
    for (const auto& [key, value] : *table_)
      if (!known_.count(std::string(key.str())) && !value.is_table())
        throw InputError(source_ + ": unknown key \"" + std::string(key.str()) + "\" in [" + name_ + "]");
  }

 private:
  [[noreturn]] void fail(const char* key, const char* what) const {
    throw InputError(source_ + ": [" + name_ + "] " + key + " " + what);
  }
  const toml::table* table_;
  std::string name_, source_;
  std::set<std::string> known_;
};

toml::table parse(const std::string& text, const std::string& source) {
  try {
    return toml::parse(text, source);
  } catch (const toml::parse_error& e) {
    std::ostringstream msg;
    // Same wording as the server's settings (server/server_settings.cpp keeps
    // its own copy: the server core must not link the engine through here).
    msg << source << ": TOML parse error at line " << e.source().begin.line << ": " << e.description();
    throw InputError(msg.str());
  }
}

std::string read_file(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path.string() + ": cannot open the configuration file");
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

const toml::table* sub(const toml::table& root, const char* a, const char* b = nullptr) {
  const toml::table* t = root[a].as_table();
  if (t && b) t = (*t)[b].as_table();
  return t;
}

void read_mesh(const toml::table& root, const std::string& src, MeshingParameters& p) {
  Section s(sub(root, "mesh"), "mesh", src);
  s.read("facet_angle_deg", p.facet_angle_deg);
  s.read("facet_size_mm", p.facet_size_mm);
  s.read("facet_distance_mm", p.facet_distance_mm);
  s.read("cell_size_mm", p.cell_size_mm);
  s.read("cell_radius_edge_ratio", p.cell_radius_edge_ratio);
  s.read("optimise", p.optimise);
  s.read("random_seed", p.random_seed);
  s.finish();
}

SolverKind solver_from(const std::string& name, const std::string& src) {
  if (name == "direct") return SolverKind::direct_cholesky;
  if (name == "cg_gamg") return SolverKind::cg_gamg;
  if (name == "gmres_bjacobi") return SolverKind::gmres_bjacobi;
  throw InputError(src + ": [elastic] solver \"" + name + "\" is not one of direct, cg_gamg, gmres_bjacobi");
}

DirichletMethod dirichlet_from(const std::string& name, const std::string& src) {
  if (name == "symmetric_elimination") return DirichletMethod::symmetric_elimination;
  if (name == "row_replacement") return DirichletMethod::row_replacement;
  throw InputError(src + ": [elastic] dirichlet \"" + name + "\" is not symmetric_elimination or row_replacement");
}

void read_elastic(const toml::table& root, const std::string& src, ElasticOptions& p) {
  Section s(sub(root, "elastic"), "elastic", src);
  std::string solver = "direct", dirichlet = "symmetric_elimination";
  s.read("solver", solver);
  s.read("dirichlet", dirichlet);
  s.read("direct_package", p.direct_package);
  s.read("rtol", p.rtol);
  s.read("max_iterations", p.max_iterations);
  s.read("petsc_options", p.petsc_options);
  s.finish();
  p.solver = solver_from(solver, src);
  p.dirichlet = dirichlet_from(dirichlet, src);
  if (p.direct_package != "cholmod" && p.direct_package != "mumps")
    throw InputError(src + ": [elastic] direct_package must be cholmod or mumps");
}

void read_affine(const toml::table& root, const std::string& src, AffineRegistrationParameters& p) {
  Section s(sub(root, "affine"), "affine", src);
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
  s.finish();
}

void read_surface(const toml::table& root, const char* which, const std::string& src,
                  ActiveSurfaceParameters& p, double* min_cavity_ml = nullptr) {
  Section s(sub(root, "surface", which), std::string("surface.") + which, src);
  if (min_cavity_ml) s.read("min_cavity_ml", *min_cavity_ml);
  s.read("max_iterations", p.max_iterations);
  s.read("step", p.step);
  s.read("membrane_stiffness", p.membrane_stiffness);
  s.read("convergence_tolerance_mm", p.convergence_tolerance_mm);
  s.read("convergence_iterations", p.convergence_iterations);
  s.read("max_step_mm", p.max_step_mm);
  s.read("force_smoothing_mm", p.force_smoothing_mm);
  s.read("edge_weight", p.edge_weight);
  s.read("edge_search_mm", p.edge_search_mm);
  s.read("contact_fraction", p.contact_fraction);
  s.read("capture_range_mm", p.capture_range_mm);
  s.finish();
  if (!(p.contact_fraction > 0 && p.contact_fraction < 1))
    throw InputError(src + ": [surface." + which + "] contact_fraction must be in (0, 1)");
  if (!(p.capture_range_mm >= 0))
    throw InputError(src + ": [surface." + which + "] capture_range_mm must be >= 0 (0: unlimited)");
}

void read_surface_repair(const toml::table& root, const std::string& src, SurfaceRepairParameters& p) {
  Section s(sub(root, "surface", "repair"), "surface.repair", src);
  s.read("enabled", p.enabled);
  s.read("unreliable_residual_mm", p.unreliable_residual_mm);
  s.read("rounds", p.rounds);
  s.read("min_component_area_mm2", p.min_component_area_mm2);
  s.read("smoothing_mm", p.smoothing_mm);
  s.read("max_search_mm", p.max_search_mm);
  s.read("max_defect_area_fraction", p.max_defect_area_fraction);
  s.finish();
  if (!(p.unreliable_residual_mm > 0) || p.rounds < 1 || p.rounds > 50 || !(p.min_component_area_mm2 >= 0) ||
      !(p.smoothing_mm > 0) || !(p.max_search_mm >= 3 * p.smoothing_mm) ||
      !(p.max_defect_area_fraction > 0 && p.max_defect_area_fraction < 1))
    throw InputError(src + ": [surface.repair] needs unreliable_residual_mm > 0, rounds in 1..50, "
                     "min_component_area_mm2 >= 0, smoothing_mm > 0, max_search_mm >= 3 x smoothing_mm and "
                     "max_defect_area_fraction in (0, 1)");
}

// Ranges are the engine's (validation_error names the key); checked here too
// so a bad value is refused when the file is read, not at the first scan.
void read_intensity(const toml::table& root, const std::string& src, IntensityRefinementParameters& p) {
  Section s(sub(root, "intensity"), "intensity", src);
  s.read("enabled", p.enabled);
  s.read("lattice_spacing_mm", p.lattice_spacing_mm);
  s.read("iterations", p.iterations);
  s.read("convergence_mm", p.convergence_mm);
  s.read("membrane_weight", p.membrane_weight);
  s.read("shrink_weight_per_mm2", p.shrink_weight_per_mm2);
  s.read("max_correction_mm", p.max_correction_mm);
  s.read("max_step_mm", p.max_step_mm);
  s.read("sample_spacing_mm", p.sample_spacing_mm);
  s.read("max_samples", p.max_samples);
  s.read("boundary_margin_mm", p.boundary_margin_mm);
  s.read("robust_scale", p.robust_scale);
  s.read("bias_degree", p.bias_degree);
  s.read("outside_fade_mm", p.outside_fade_mm);
  s.read("min_explained_variance", p.min_explained_variance);
  s.finish();
  const std::string error = validation_error(p);
  if (!error.empty()) throw InputError(src + ": [intensity] " + error);
}

void read_rest(const toml::table& root, const std::string& src, PipelineParameters& p) {
  Section field(sub(root, "field"), "field", src);
  field.read("blend_distance_mm", p.field.blend_distance_mm);
  field.read("barycentric_tolerance", p.field.barycentric_tolerance);
  field.read("smoothing_sweeps", p.field.smoothing_sweeps);
  field.finish();
  Section models(sub(root, "models"), "models", src);
  models.read("presmooth_sigma_mm", p.models.presmooth_sigma_mm);
  models.read("taubin_iterations", p.models.taubin_iterations);
  models.read("taubin_lambda", p.models.taubin_lambda);
  models.read("taubin_mu", p.models.taubin_mu);
  models.finish();
  Section gates(sub(root, "gates"), "gates", src);
  gates.read("min_jacobian_determinant", p.gates.min_jacobian_determinant);
  gates.read("max_mean_surface_residual_mm", p.gates.max_mean_surface_residual_mm);
  gates.read("min_intraop_brain_fraction", p.gates.min_intraop_brain_fraction);
  gates.finish();
  Section limits(sub(root, "limits"), "limits", src);
  limits.read("max_image_bytes", p.max_image_bytes);
  limits.finish();
}

LabelTable label_table_from(const toml::table& root, const std::string& src) {
  const toml::array* entries = root["label"].as_array();
  if (!entries || entries->empty()) throw InputError(src + ": no [[label]] entries");
  LabelTable table;
  for (const auto& node : *entries) {
    const toml::table* t = node.as_table();
    if (!t) throw InputError(src + ": every label entry must be a [[label]] table");
    LabelEntry e;
    std::string role = "structure";
    std::int64_t value = -1;
    std::string colour;
    Section s(t, "label", src);
    s.read("value", value);
    s.read("name", e.name);
    s.read("short_name", e.short_name);
    s.read("role", role);
    s.read("youngs_modulus_pa", e.youngs_modulus_pa);
    s.read("poisson_ratio", e.poisson_ratio);
    s.read("model", e.make_model);
    s.read("resectable", e.resectable);
    s.read("colour", colour);
    s.finish();
    if (value < 1 || value > 65535) throw InputError(src + ": label value must be in 1..65535");
    e.value = static_cast<std::uint16_t>(value);
    try {
      e.colour = colour.empty() ? default_label_colour(e.value) : label_colour_from_hex(colour);
    } catch (const InputError& err) {
      throw InputError(src + ": [[label]] " + e.name + ": " + err.what());
    }
    e.role = label_role_from_string(role);
    table.entries.push_back(e);
  }
  table.validate();
  return table;
}

PipelineParameters parameters_from(const toml::table& root, const std::string& src,
                                   const std::filesystem::path* base_dir) {
  static const std::set<std::string> sections = {"server", "security", "openigtlink", "mesh", "elastic", "affine", "surface",
                                                 "field", "intensity", "models", "gates", "limits", "label"};
  for (const auto& [key, value] : root)
    if (!sections.count(std::string(key.str())) && key.str() != "label_table")
      throw InputError(src + ": unknown top-level key or section \"" + std::string(key.str()) + "\"");
  PipelineParameters p;
  if (root["label"]) {
    p.label_table = label_table_from(root, src);
  } else if (auto path = root["label_table"].value<std::string>()) {
    if (base_dir) {
      const auto full = std::filesystem::path(*path).is_absolute() ? std::filesystem::path(*path) : *base_dir / *path;
      p.label_table = label_table_from_text(read_file(full), full.string());
    } else if (*path == "labels.toml") {
      p.label_table = label_table_from_text(embedded_labels_toml(), "built-in labels.toml");
    } else {
      throw InputError(src + ": label_table \"" + *path + "\" cannot be resolved without a file location");
    }
  } else {
    p.label_table = label_table_from_text(embedded_labels_toml(), "built-in labels.toml");
  }
  read_mesh(root, src, p.meshing);
  read_elastic(root, src, p.elastic);
  read_affine(root, src, p.affine);
  read_surface(root, "outer", src, p.outer_surface);
  read_surface(root, "ventricles", src, p.ventricle_surface);
  read_surface(root, "resection", src, p.resection_surface, &p.min_resection_cavity_ml);
  if (!(p.min_resection_cavity_ml > 0))
    throw InputError(src + ": [surface.resection] min_cavity_ml must be > 0");
  read_surface_repair(root, src, p.surface_repair);
  read_intensity(root, src, p.intensity);
  read_rest(root, src, p);
  return p;
}

}  // namespace

const std::string& default_config_text() { return embedded_brainshiftd_toml(); }

PipelineParameters pipeline_parameters_from_file(const std::filesystem::path& path) {
  const std::string src = path.string();
  const auto base = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  return parameters_from(parse(read_file(path), src), src, &base);
}

PipelineParameters pipeline_parameters_from_text(const std::string& toml_text, const std::string& source_name) {
  return parameters_from(parse(toml_text, source_name), source_name, nullptr);
}

LabelTable label_table_from_text(const std::string& toml_text, const std::string& source_name) {
  return label_table_from(parse(toml_text, source_name), source_name);
}

const LabelTable& default_label_table() {
  static const LabelTable table = label_table_from_text(embedded_labels_toml(), "built-in labels.toml");
  return table;
}

}  // namespace brainshift::config
