// Where does the registration error of a phantom case come from? Compares the
// estimated pull-back field with the phantom's true one, split by region of
// the intraop brain (near the outer surface, near the ventricles, deep), and
// prints one JSON object. A development tool: run it after changing a stage.
//   brainshift_phantom_diagnostics [--case NAME] [--config FILE]
#include <mpi.h>

#include <CLI/CLI.hpp>
#include <cstdio>
#include <memory>

#include "atlas/default_atlas.h"
#include "config_file.h"
#include "fem/petsc_session.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "phantom/brain_shift_phantom.h"
#include "field/displacement_field.h"
#include "field/metrics.h"
#include "pipeline/engine_session.h"
#include "pipeline/warm_state.h"

using namespace brainshift;

namespace {

struct Bin {
  double sum = 0, max = 0;
  std::size_t n = 0;
  void add(double e) { sum += e; max = std::max(max, e); ++n; }
  nlohmann::json json() const { return {{"mean_mm", n ? sum / n : 0.0}, {"max_mm", max}, {"voxels", n}}; }
};

}  // namespace

int main(int argc, char** argv) {
  std::string only, config_path, atlas_cache = "brainshift-atlas";
  CLI::App app("phantom error diagnostics");
  app.add_option("--case", only);
  app.add_option("--config", config_path);
  app.add_option("--atlas-cache", atlas_cache);
  CLI11_PARSE(app, argc, argv);
  PetscSession petsc;
  const PipelineParameters params = config_path.empty()
      ? config::pipeline_parameters_from_text(config::default_config_text(), "built-in")
      : config::pipeline_parameters_from_file(config_path);
  DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache);
  std::unique_ptr<WarmState> plain, with_tumor;
  nlohmann::json out = nlohmann::json::array();
  for (const auto& spec : standard_phantom_suite()) {
    if (!only.empty() && spec.name != only) continue;
    // A case that resects a tumor gets the atlas with that tumor in it.
    std::unique_ptr<WarmState>& slot = spec.preop_tumor ? with_tumor : plain;
    PreopInput preop{atlas.t1, atlas.labels};
    if (spec.preop_tumor) implant_tumor(preop.t1, preop.labels, *spec.preop_tumor);
    if (!slot || spec.preop_tumor) {
      slot.reset();
      slot = build_warm_state(MPI_COMM_WORLD, std::move(preop), params, nullptr, std::nullopt);
    }
    auto& warm = slot;
    const PhantomCase c = make_phantom(warm->preop.t1, warm->preop.labels, spec);
    const ScanResult r = run_intraop(*warm, IntraopInput{c.intraop_labels, c.intraop_t1}, params, nullptr);
    // Oracle: the true displacement at every boundary node, same affine, same
    // elastic interpolation: what is left is the interior model's own error.
    const PhantomDeformation truth(warm->preop.labels, spec);
    const TetMesh& mesh = warm->fem.mesh();
    MeshDeformation oracle;
    oracle.intraop_from_preop = r.intraop_from_preop;
    std::vector<Eigen::Vector3d> values;
    double boundary_error = 0;
    // With a resected structure, the system where its wall is fixed too.
    const int system = r.metrics.contains("resection") ? r.metrics["resection"].value("system", 0) : 0;
    for (int n : warm->fem.fixed_nodes(system)) {
      const Eigen::Vector3d p = mesh.nodes_mm[n];
      values.push_back(truth.forward(p) - oracle.apply_affine(p));
    }
    warm->fem.drive_solve(values, oracle.nonrigid_mm, system);
    const VectorImage3 oracle_field = pullback_field(mesh, oracle, c.intraop_labels.grid, params.field);
    std::vector<Eigen::Vector3d> xs, ps;
    for (const auto& [x, p] : c.landmarks_intraop_preop_mm) {
      xs.push_back(x);
      ps.push_back(p);
    }
    const TreStats oracle_tre = target_registration_error(oracle_field, xs, ps);
    const TreStats tre = target_registration_error(r.pullback_field_mm, xs, ps);
    // Landmark errors by distance (preop) from the resected region's centre.
    Bin near_resection, far_from_resection;
    if (spec.resection.enabled)
      for (std::size_t i = 0; i < xs.size(); ++i)
        ((ps[i] - truth.resection_centre_mm()).norm() < truth.resection_radius_mm() + 15 ? near_resection
                                                                                         : far_from_resection)
            .add(tre.errors_mm[i]);
    (void)boundary_error;
    const Mask brain = mask_of_labels(c.intraop_labels, {1, 2});
    const Mask ventricles = mask_of_labels(c.intraop_labels, {2});
    const ImageF depth = signed_distance_mm(brain);
    const ImageF to_ventricle = signed_distance_mm(ventricles);
    Bin surface, near_ventricle, deep, all;
    Eigen::Vector3d mean_error = Eigen::Vector3d::Zero();
    for (std::size_t v = 0; v < brain.voxels.size(); ++v) {
      if (!brain.voxels[v]) continue;
      const Eigen::Vector3d d = (r.pullback_field_mm.vectors[v] - c.true_pullback_mm.vectors[v]).cast<double>();
      const double e = d.norm();
      mean_error += d;
      all.add(e);
      if (depth.voxels[v] > -5) surface.add(e);
      else if (to_ventricle.voxels[v] < 5) near_ventricle.add(e);
      else deep.add(e);
    }
    mean_error /= std::max<std::size_t>(all.n, 1);
    out.push_back({{"case", spec.name}, {"kind", r.kind == ResultKind::nonrigid ? "nonrigid" : "fallback"},
                   {"within_5mm_of_surface", surface.json()}, {"within_5mm_of_ventricles", near_ventricle.json()},
                   {"deep", deep.json()}, {"all", all.json()},
                   {"mean_error_vector_mm", {mean_error.x(), mean_error.y(), mean_error.z()}},
                   {"tre_mean_mm", tre.mean_mm},
                   {"tre_within_15mm_of_resection", near_resection.json()},
                   {"tre_beyond_15mm_of_resection", far_from_resection.json()},
                   {"tre_mean_with_true_boundary_mm", oracle_tre.mean_mm},
                   {"tre_p95_with_true_boundary_mm", oracle_tre.p95_mm},
                   {"metrics", r.metrics}});
  }
  std::printf("%s\n", out.dump(1).c_str());
  return 0;
}
