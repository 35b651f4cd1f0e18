// Benchmark of the volumetric elastic engine on the Colin27 brain, phase by
// phase as in the published Figure 6. Prints one JSON object (rank 0).
//
//   mpirun -np 2 brainshift_fem_bench --solver direct --cell-size 3.4
//
// The boundary data is a synthetic brain shift: the cortex sinks along gravity
// under a craniotomy (up to --sink-mm, Gaussian fall-off away from it) and the
// ventricle walls follow with a fifth of it.
#include <mpi.h>
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <nlohmann/json.hpp>

#include "atlas/default_atlas.h"
#include "core/timer.h"
#include "fem/elastic_model.h"
#include "fem/petsc_session.h"
#include "mesh/label_mesher.h"
#include "mesh/mesh_quality.h"
#include "mesh/surface_extraction.h"
#include "mesh/vtk_io.h"
#include "pipeline/mpi_commands.h"

using namespace brainshift;

namespace {

struct Options {
  std::string solver = "direct", package = "cholmod", dirichlet = "symmetric_elimination";
  std::string atlas_cache = "brainshift-atlas", vtu;
  double cell_size_mm = 3.4, facet_size_mm = 2.0, facet_distance_mm = 1.5;
  double sink_mm = 12.0;
  int repeat = 5;
};

double peak_rss_mb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

SolverKind solver_kind(const std::string& s) {
  if (s == "cg_gamg") return SolverKind::cg_gamg;
  if (s == "gmres_bjacobi") return SolverKind::gmres_bjacobi;
  return SolverKind::direct_cholesky;
}

// Craniotomy at the top of the left frontal lobe, gravity pointing down (-z:
// patient supine would be -y; any direction exercises the same solve).
std::vector<Eigen::Vector3d> brain_shift_values(const TetMesh& mesh, const std::vector<int>& fixed,
                                                double sink_mm, double phase) {
  Eigen::Vector3d top = Eigen::Vector3d::Constant(-1e9);
  for (const auto& p : mesh.nodes_mm) top = top.cwiseMax(p);
  const Eigen::Vector3d centre(-30.0 + phase, 20.0, top.z());
  const Eigen::Vector3d gravity(0, 0, -1);
  std::vector<char> on_outer(mesh.node_count(), 0);
  for (const auto& f : mesh.boundary_faces)
    if (f.neighbour_label == 0)
      for (int n : f.nodes) on_outer[n] = 1;
  std::vector<Eigen::Vector3d> values;
  values.reserve(fixed.size());
  const double sigma = 35.0;
  for (int n : fixed) {
    const double r2 = (mesh.nodes_mm[n] - centre).squaredNorm();
    const double fall = std::exp(-r2 / (2 * sigma * sigma));
    values.push_back(gravity * sink_mm * fall * (on_outer[n] ? 1.0 : 0.2));
  }
  return values;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  CLI::App app("brainshift FEM benchmark (Figure-6 phases), JSON on stdout");
  app.add_option("--solver", o.solver, "direct | cg_gamg | gmres_bjacobi");
  app.add_option("--package", o.package, "cholmod | mumps (direct solver)");
  app.add_option("--dirichlet", o.dirichlet, "symmetric_elimination | row_replacement");
  app.add_option("--cell-size", o.cell_size_mm);
  app.add_option("--facet-size", o.facet_size_mm);
  app.add_option("--facet-distance", o.facet_distance_mm);
  app.add_option("--sink-mm", o.sink_mm);
  app.add_option("--repeat", o.repeat, "solves with new boundary values");
  app.add_option("--atlas-cache", o.atlas_cache);
  app.add_option("--vtu", o.vtu, "write the deformed mesh here");
  CLI11_PARSE(app, argc, argv);

  PetscSession petsc;
  int rank = 0, size = 1;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  MPI_Comm_size(MPI_COMM_WORLD, &size);

  TetMesh mesh;
  nlohmann::json out;
  Stopwatch clock;
  if (rank == 0) {
    const DefaultAtlas atlas = load_or_build_default_atlas(o.atlas_cache);
    out["atlas_seconds"] = clock.lap();
    MeshingParameters mp;
    mp.cell_size_mm = o.cell_size_mm;
    mp.facet_size_mm = o.facet_size_mm;
    mp.facet_distance_mm = o.facet_distance_mm;
    mesh = mesh_label_image(atlas.labels, mp);
    out["mesh_seconds"] = clock.lap();
    const MeshQuality q = measure_quality(mesh);
    out["mesh_quality"] = {{"min_dihedral_deg", q.min_dihedral_deg}, {"max_dihedral_deg", q.max_dihedral_deg},
                           {"inverted_tets", q.inverted_tets}, {"volume_ml", q.total_volume_mm3 / 1000.0}};
  }
  clock.lap();
  mpi_channel::broadcast(MPI_COMM_WORLD, mesh);
  std::vector<int> fixed = boundary_nodes(mesh);
  const double broadcast_seconds = clock.lap();

  ElasticOptions eo;
  eo.solver = solver_kind(o.solver);
  eo.direct_package = o.package;
  eo.rtol = 1e-8;
  if (o.dirichlet == "row_replacement") eo.dirichlet = DirichletMethod::row_replacement;
  Stopwatch total;
  ElasticModel model(MPI_COMM_WORLD, mesh, fixed, eo);
  model.assemble();
  model.setup_solver();
  std::vector<Eigen::Vector3d> u;
  SolveReport first = model.solve(brain_shift_values(mesh, fixed, o.sink_mm, 0.0), u);
  const PhaseTimes first_times = model.times();
  const double total_seconds = total.seconds();
  // Warm solves: new boundary values, same factorisation / preconditioner.
  std::vector<double> warm;
  for (int r = 1; r <= o.repeat; ++r) {
    Stopwatch s;
    model.solve(brain_shift_values(mesh, fixed, o.sink_mm * (1.0 + 0.05 * r), 2.0 * r), u);
    warm.push_back(s.seconds());
  }
  std::sort(warm.begin(), warm.end());
  double max_u = 0;
  for (const auto& v : u) max_u = std::max(max_u, v.norm());
  double rss = peak_rss_mb(), rss_sum = 0;
  MPI_Reduce(&rss, &rss_sum, 1, MPI_DOUBLE, MPI_SUM, 0, MPI_COMM_WORLD);

  if (rank == 0) {
    if (!o.vtu.empty()) write_vtu(o.vtu, mesh, &u);
    out["nodes"] = mesh.node_count();
    out["tets"] = mesh.tet_count();
    out["unknowns"] = 3 * mesh.node_count();
    out["fixed_nodes"] = fixed.size();
    out["ranks"] = size;
    out["solver"] = model.solver_description();
    out["blas"] = to_string(loaded_blas().kind);
    out["phases_seconds"] = {{"create", first_times.create + broadcast_seconds},
                             {"assemble", first_times.assemble},
                             {"boundary_conditions", first_times.boundary},
                             {"setup_factorise", first_times.setup},
                             {"solve", first_times.solve},
                             {"gather", first_times.gather},
                             {"total", total_seconds + broadcast_seconds}};
    out["first_solve"] = {{"iterations", first.iterations}, {"relative_residual", first.relative_residual}};
    out["warm_solve_seconds"] = {{"min", warm.empty() ? 0 : warm.front()},
                                 {"median", warm.empty() ? 0 : warm[warm.size() / 2]},
                                 {"max", warm.empty() ? 0 : warm.back()}};
    out["max_displacement_mm"] = max_u;
    out["peak_rss_mb_all_ranks"] = rss_sum;
    std::printf("%s\n", out.dump().c_str());
  }
  return 0;
}
