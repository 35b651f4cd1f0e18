// The preop phase: mesh, boundary surfaces, FEM set-up on all ranks, affine
// samples, surface models bound to the mesh. Minutes are allowed here; every
// per-scan cost that can move here does.
#include <algorithm>
#include <future>
#include <map>

#include "core/errors.h"
#include "core/timer.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "mesh/surface_contacts.h"
#include "mesh/surface_extraction.h"
#include "models/surface_models.h"
#include "pipeline/plausibility_stage.h"
#include "pipeline/warm_state.h"
#include "registration/intensity_refinement.h"
#include "protocol/stage_names.h"

namespace brainshift {
namespace {

namespace stages = protocol::stages;

// Stage names from protocol/stage_names.h, the one vocabulary.
void report(const ProgressFn& progress, std::string_view stage, double fraction, double seconds) {
  if (progress) progress(std::string(stage), fraction, seconds);
}

ElasticOptions elastic_options_for(const PipelineParameters& params) {
  ElasticOptions options = params.elastic;
  for (const auto& e : params.label_table.entries)
    if (e.role != LabelRole::cavity)
      options.material_by_label[e.value] = Material{e.youngs_modulus_pa, e.poisson_ratio};
  const auto* brain = params.label_table.find(params.label_table.brain_label());
  options.default_material = Material{brain->youngs_modulus_pa, brain->poisson_ratio};
  return options;
}

// Facing walls closer than this are kept apart during the match (pairs
// farther apart may close by contact_fraction x 8 mm = 3.2 mm or more, which
// brain shift's own compression of a sulcus or a ventricle stays within).
constexpr double kContactMaxGapMm = 8.0;

std::vector<MatchedSurface> matched_surfaces(const TetMesh& mesh, const LabelTable& table) {
  std::vector<MatchedSurface> out;
  out.push_back({"outer", 0, extract_boundary_surface(mesh, 0), {}});
  if (out.front().surface.triangles.empty())
    throw ComputeError("the brain mesh has no outer boundary surface");
  for (const auto cavity : table.cavity_labels()) {
    TriSurface wall = extract_boundary_surface(mesh, cavity);
    // Boundary faces point out of the tissue, i.e. into the cavity; the
    // surface matcher expects normals pointing out of the structure it is
    // matched to (the cavity), so the wall is turned around.
    for (auto& t : wall.triangles) std::swap(t[1], t[2]);
    if (!wall.triangles.empty()) out.push_back({table.find(cavity)->name, cavity, std::move(wall), {}});
  }
  for (auto& s : out) s.contacts = facing_vertex_pairs(s.surface, kContactMaxGapMm);
  return out;
}

std::vector<int> index_of_nodes(std::size_t node_count, const std::vector<int>& nodes) {
  std::vector<int> index(node_count, -1);
  for (std::size_t i = 0; i < nodes.size(); ++i) index[nodes[i]] = static_cast<int>(i);
  return index;
}

// Resectable labels present in the preop labels (a few voxels are noise, not
// a structure whose removal moves the brain).
// label -> its volume (ml).
std::map<std::uint16_t, double> present_resectables(const LabelImage& labels, const LabelTable& table) {
  std::map<std::uint16_t, double> out;
  for (const auto l : table.resectable_labels()) {
    const double ml = volume_ml(mask_of_labels(labels, {l}));
    if (ml >= 0.1) out[l] = ml;
  }
  return out;
}

// For each resectable structure with a wall in the mesh: the wall surface and
// a fixed-node set (the boundary plus the wall) for a system of its own.
std::vector<ResectableWall> resectable_walls(const TetMesh& mesh, const LabelTable& table,
                                             const std::map<std::uint16_t, double>& present,
                                             const std::vector<int>& boundary,
                                             std::vector<std::vector<int>>& fixed_sets) {
  std::vector<ResectableWall> out;
  for (const auto& [l, ml] : present) {
    TriSurface wall = extract_interface_surface(mesh, l);
    if (wall.triangles.empty()) continue;  // the structure touches no other tissue
    std::vector<int> fixed = boundary;
    fixed.insert(fixed.end(), wall.mesh_node.begin(), wall.mesh_node.end());
    std::sort(fixed.begin(), fixed.end());
    fixed.erase(std::unique(fixed.begin(), fixed.end()), fixed.end());
    if (fixed.size() == boundary.size()) continue;  // wall entirely on the boundary
    ResectableWall r;
    r.name = table.find(l)->name;
    r.label = l;
    r.wall = std::move(wall);
    r.system = static_cast<int>(fixed_sets.size());
    r.fixed_index_of_node = index_of_nodes(mesh.node_count(), fixed);
    r.volume_ml = ml;
    fixed_sets.push_back(std::move(fixed));
    out.push_back(std::move(r));
  }
  return out;
}

// The whole-brain model (every label inside the outer surface) takes the
// parenchyma's name from the table: the gateway, the default pull and the
// Slicer scene look it up by that name.
std::vector<StructureDefinition> structures_for(const LabelTable& table) {
  StructureDefinition brain{table.find(table.brain_label())->name, {}};
  std::vector<StructureDefinition> out;
  for (const auto& e : table.entries) {
    brain.labels.push_back(e.value);
    if (e.make_model && e.role != LabelRole::parenchyma) out.push_back({e.name, {e.value}});
  }
  out.insert(out.begin(), brain);
  return out;
}

// How much work the bounded meshing did (engine/mesh/README.md): reported
// next to the preop timings so a mesh that hit a budget is visible.
nlohmann::json meshing_report(const MeshingStats& s) {
  return {{"refine_seconds", s.seconds_refine},
          {"optimise_seconds", s.seconds_optimise},
          {"refined_vertices", s.refined_vertices},
          {"vertex_cap", s.vertex_cap},
          {"exude_steps", s.exude_steps},
          {"exude_budget", s.exude_budget},
          {"exude_budget_hit", s.exude_budget_hit},
          {"slivers_before", s.slivers_before},
          {"slivers_after", s.slivers_after},
          {"min_dihedral_before_deg", s.min_dihedral_before_deg},
          {"min_dihedral_after_deg", s.min_dihedral_after_deg}};
}

}  // namespace

std::unique_ptr<WarmState> build_warm_state(MPI_Comm comm, PreopInput input,
                                            const PipelineParameters& params,
                                            const ProgressFn& progress,
                                            std::optional<TetMesh> stored_mesh) {
  const LabelTable& table = params.label_table;
  validate_preop_input(input, table);
  auto warm = std::make_unique<WarmState>(comm);
  Stopwatch total;

  Stopwatch stage;
  report(progress, stages::kMesh, 0.0, 0.0);
  MeshingParameters meshing = params.meshing;
  meshing.cavity_labels = table.cavity_labels();
  meshing.default_tissue_label = table.brain_label();
  const std::map<std::uint16_t, double> resectable = present_resectables(input.labels, table);
  for (const auto& [l, ml] : resectable) meshing.interface_labels.push_back(l);
  // Progress inside meshing: refinement takes most of it (README.md of
  // engine/mesh), exudation is bounded, assembly is short.
  MeshingStats mesh_stats;
  const MeshingProgressFn mesh_progress = [&](const std::string& step, const MeshingStats&) {
    report(progress, stages::kMesh, step == "refine" ? 0.7 : 0.9, stage.seconds());
  };
  const bool meshed = !stored_mesh;
  TetMesh mesh = stored_mesh ? std::move(*stored_mesh)
                             : mesh_label_image(input.labels, meshing, &mesh_stats, mesh_progress);
  const double mesh_seconds = stage.lap();
  report(progress, stages::kMesh, 1.0, mesh_seconds);

  std::vector<int> fixed_nodes = boundary_nodes(mesh);
  // A brain label of a few voxels meshes to a handful of tets with every node
  // on the surface: nothing for the FEM to solve. That is bad input, and is
  // said so here instead of surfacing later as a solver failure.
  if (mesh.tet_count() == 0 || fixed_nodes.size() >= mesh.node_count())
    throw InputError("preop labels: the brain is too small to mesh (" + std::to_string(mesh.node_count()) +
                     " mesh nodes, none inside); check the brain label");
  warm->surfaces = matched_surfaces(mesh, table);
  warm->fixed_index_of_node = index_of_nodes(mesh.node_count(), fixed_nodes);
  std::vector<std::vector<int>> fixed_sets;
  fixed_sets.push_back(fixed_nodes);
  warm->resectables = resectable_walls(mesh, table, resectable, fixed_nodes, fixed_sets);

  // The models need only the labels and the mesh, not the FEM systems: they
  // are made on a second thread while the systems are assembled and
  // factorised (one core at one rank), which takes them off the warm-up's
  // critical path (a restart from the stored mesh: ~2-3 s of ~10).
  const auto ventricles = table.cavity_labels();
  struct Models {
    PreopBoundarySamples affine_samples;
    std::map<std::string, PreopModel> models;
    double brain_volume_ml = 0;
    PlausibilityPreop plausibility;
    IntensityPlacementPreop intensity_placement;
    double seconds = 0;
  };
  auto models_job = std::async(std::launch::async, [&input, &table, &params, &mesh, &ventricles] {
    Stopwatch watch;
    Models m;
    m.affine_samples = prepare_preop_samples(input.labels, table.brain_label(),
                                             ventricles.empty() ? std::uint16_t{0} : ventricles.front());
    for (auto& [name, surface] : structure_models(input.labels, structures_for(table), params.models)) {
      PreopModel model{std::move(surface), {}};
      model.binding = bind_to_mesh(model.surface, mesh);
      m.models.emplace(name, std::move(model));
    }
    m.brain_volume_ml = volume_ml(outline_mask(input.labels));
    m.plausibility = plausibility_preop(input.labels, table);
    // What placing the preop by intensity compares (a brain-extracted preop
    // or scan, and the check of every head placement; segmentation_rounds.h):
    // the T1 smoothed twice, 0.7 s, here rather than on the first scan.
    m.intensity_placement = intensity_placement_preop(input.t1, nonzero_mask(input.labels));
    m.seconds = watch.seconds();
    return m;
  });

  report(progress, stages::kFactorise, 0.0, 0.0);
  double fem_seconds = 0;
  try {
    // A copy: the models thread reads `mesh` meanwhile.
    warm->fem.drive_load(TetMesh(mesh), std::move(fixed_sets), elastic_options_for(params));
    fem_seconds = stage.lap();
  } catch (...) {
    models_job.wait();
    throw;
  }
  // Every system (one per resectable wall beyond the first) costs its own
  // assembly and factorisation.
  double assemble_seconds = 0, factorise_seconds = 0;
  for (int i = 0; i < warm->fem.system_count(); ++i) {
    const auto& times = warm->fem.model(i).times();
    assemble_seconds += times.create + times.assemble;
    factorise_seconds += times.setup;
  }
  report(progress, stages::kFactorise, 1.0, fem_seconds);

  report(progress, stages::kPreopModels, 0.0, 0.0);
  Models models = models_job.get();
  warm->affine_samples = std::move(models.affine_samples);
  warm->models = std::move(models.models);
  warm->brain_volume_ml = models.brain_volume_ml;
  warm->plausibility_preop = std::move(models.plausibility);
  warm->intensity_placement_preop = std::move(models.intensity_placement);
  // What the models cost beyond the factorisation (their own time is
  // "surfaces_and_models_work").
  const double models_seconds = stage.lap();
  report(progress, stages::kPreopModels, 1.0, models_seconds);

  warm->timings = {{std::string(stages::kMesh), mesh_seconds},
                   {std::string(stages::kAssemble), assemble_seconds},
                   {std::string(stages::kFactorise), factorise_seconds},
                   {"surfaces_and_models", models_seconds},
                   {"surfaces_and_models_work", models.seconds},
                   {std::string(stages::kTotal), total.seconds()}};
  if (meshed) warm->timings["meshing"] = meshing_report(mesh_stats);
  warm->preop = std::move(input);
  return warm;
}

const ImageF& preop_t1_at_resolution(WarmState& warm, const Grid3& grid) {
  auto& kept = warm.preop_t1_blurred;
  const Eigen::Vector3d sigma = preop_point_spread_sigma_voxels(warm.preop.t1.grid, grid);
  for (const auto& b : kept)
    if ((b.sigma_voxels - sigma).cwiseAbs().maxCoeff() < 1e-9) return b.t1;
  if (kept.size() >= 2) kept.erase(kept.begin());
  kept.push_back({sigma, preop_at_intraop_resolution(warm.preop.t1, grid)});
  return kept.back().t1;
}

}  // namespace brainshift
