// Timing driver: assemble + set up + several warm solves on a structured box.
//   mpirun -np 2 box_solver_timing <cells> <direct|cg|gmres> <elim|rows> [cholmod|mumps] [nu]
// Prints the slowest rank's time for each phase (the one the user waits for).
#include <mpi.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "box_mesh.h"
#include "fem/elastic_model.h"
#include "fem/petsc_session.h"

using namespace brainshift;

static double slowest(double t) {
  MPI_Allreduce(MPI_IN_PLACE, &t, 1, MPI_DOUBLE, MPI_MAX, MPI_COMM_WORLD);
  return t;
}

int main(int argc, char** argv) {
  if (argc < 4) {
    std::fprintf(stderr, "usage: box_solver_timing <cells> <direct|cg|gmres> <elim|rows> [cholmod|mumps] [nu]\n");
    return 2;
  }
  MPI_Init(&argc, &argv);
  int rank = 0;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  {
    PetscSession petsc;
    const int cells = std::atoi(argv[1]);
    const std::string solver = argv[2], method = argv[3];
    ElasticOptions o;
    o.solver = solver == "cg" ? SolverKind::cg_gamg
               : solver == "gmres" ? SolverKind::gmres_bjacobi : SolverKind::direct_cholesky;
    o.dirichlet = method == "rows" ? DirichletMethod::row_replacement : DirichletMethod::symmetric_elimination;
    if (argc > 4) o.direct_package = argv[4];
    if (argc > 5) o.default_material.poisson_ratio = std::atof(argv[5]);
    o.rtol = 1e-8;
    // ~1.7 mm spacing: the size of the real brain mesh's elements.
    const auto box = test::make_box_mesh({cells, cells, cells}, Eigen::Vector3d::Zero(),
                                         Eigen::Vector3d::Constant(1.7 * cells));
    if (rank == 0) {
      const BlasInfo blas = loaded_blas();
      std::printf("nodes %zu tets %zu fixed %zu ranks %s BLAS %s (%s)\n", box.mesh.node_count(),
                  box.mesh.tet_count(), box.boundary_nodes.size(), std::getenv("OMPI_COMM_WORLD_SIZE") ? std::getenv("OMPI_COMM_WORLD_SIZE") : "1",
                  to_string(blas.kind), blas.library_path.c_str());
    }
    ElasticModel model(MPI_COMM_WORLD, box.mesh, box.boundary_nodes, o);
    model.assemble();
    model.setup_solver();
    const PhaseTimes t = model.times();
    const double create = slowest(t.create), assemble = slowest(t.assemble), setup = slowest(t.setup);
    if (rank == 0)
      std::printf("%s: create %.3f s assemble %.3f s setup %.3f s\n", model.solver_description().c_str(),
                  create, assemble, setup);
    std::vector<Eigen::Vector3d> u;
    for (int k = 0; k < 4; ++k) {
      std::vector<Eigen::Vector3d> values;
      for (int v : box.boundary_nodes) {
        const Eigen::Vector3d& x = box.mesh.nodes_mm[v];
        values.emplace_back(0.5 * std::sin(0.1 * x.x() + k), 0.3 * std::cos(0.07 * x.y() - k), 0.2 * std::sin(0.05 * x.z() * (k + 1)));
      }
      const SolveReport r = model.solve(values, u);
      const PhaseTimes s = model.times();
      const double total = slowest(r.seconds), rhs = slowest(s.boundary), solve = slowest(s.solve), gather = slowest(s.gather);
      if (rank == 0)
        std::printf("solve %d: total %.3f s (rhs %.4f, solve %.3f, residual+gather %.4f) its %d rel.res %.1e factorisations %d\n",
                    k, total, rhs, solve, gather, r.iterations, r.relative_residual, model.factorisation_count());
    }
  }
  MPI_Finalize();
  return 0;
}
