#pragma once
// Linear-elastic FEM model of a labeled tet mesh, solved with PETSc over MPI.
//
// Lifecycle (every call is collective on the communicator):
//   ElasticModel model(comm, mesh, fixed_nodes, options);  // layout + preallocation
//   model.assemble();        // global stiffness, once
//   model.setup_solver();    // reduced/row-replaced system + factorisation/PC, once
//   model.solve(values, u);  // per new set of boundary values: one mat-vec + solve
//
// Partition: the mesh is replicated on every rank and its nodes are already
// ordered along a space-filling curve by the mesher, so contiguous node ranges
// are compact regions with short interfaces. Rank r owns the rows of the
// nodes in its range; the range comes from PETSc's own split (PetscLayout with
// block size 3), so it always agrees with the vectors PETSc creates. Each rank
// assembles the tets whose lowest-numbered node it owns (each tet exactly
// once); rows of the other nodes of such a tet may live on another rank and
// travel through PETSc's stash during MatAssemblyEnd.
#include <mpi.h>

#include <Eigen/Dense>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/tet_mesh.h"
#include "fem/element.h"

namespace brainshift {

enum class DirichletMethod {
  // Default. Solve the reduced SPD system on the free dofs,
  //   A_ff u_f = f_f - A_fb u_b,
  // with A_ff and A_fb extracted once. Its Cholesky factor is ~1.7x smaller
  // than that of the row/column-zeroed full matrix (docs/DESIGN.md, "Measured facts").
  symmetric_elimination,
  // The published approach: replace each fixed row by the identity row and
  // put the value in the rhs. The matrix is no longer symmetric, so only LU
  // (direct_cholesky then runs LU) and GMRES are valid with it.
  row_replacement,
};

enum class SolverKind {
  // Factorise once (Cholesky; LU with row_replacement); each new boundary set
  // is one forward/back substitution.
  direct_cholesky,
  // CG + GAMG with the rigid-body near-null space of the free nodes, warm-
  // started from the previous solution. Needs symmetric_elimination.
  cg_gamg,
  // GMRES + block Jacobi with ILU(0) sub-solves (the published choice), for
  // comparison. ILU(0) breaks down at nu = 0.49, so a positive-definite shift
  // is always set.
  gmres_bjacobi,
};

struct ElasticOptions {
  std::map<int, Material> material_by_label;  // tet label -> material
  Material default_material;                  // labels not in the map
  DirichletMethod dirichlet = DirichletMethod::symmetric_elimination;
  SolverKind solver = SolverKind::direct_cholesky;
  // Sparse direct package: "cholmod" (SuiteSparse, sequential) or "mumps".
  // On more than one rank CHOLMOD cannot factor a distributed matrix, so
  // "cholmod" then means: gather the reduced matrix onto every rank
  // (PCREDUNDANT) and factor it there with CHOLMOD; "mumps" factors it
  // distributed. With row_replacement (LU) "cholmod" selects UMFPACK.
  std::string direct_package = "cholmod";
  double rtol = 1e-10;  // iterative solvers: relative residual tolerance
  int max_iterations = 10000;
  // Extra PETSc options for this model's solver, all under the prefix "fem_"
  // so configuration can override our defaults, e.g.
  // "-fem_pc_factor_mat_solver_type mumps -fem_ksp_monitor". They are applied
  // in a private options database and do not leak into other models.
  std::string petsc_options;
};

struct PhaseTimes {  // wall-clock seconds, rank-local
  double create = 0;    // layout, node graph, preallocation
  double assemble = 0;  // element stiffness + MatAssembly
  double setup = 0;     // sub-matrices / row replacement + factorisation or PC set-up
  double boundary = 0;  // last solve: rhs from boundary values (one mat-vec)
  double solve = 0;     // last solve: KSPSolve
  double gather = 0;    // last solve: residual check + field gathered to all ranks
};

struct SolveReport {
  int iterations = 0;
  double residual_norm = 0;      // true residual ||b - A x|| of the system solved
  double relative_residual = 0;  // residual_norm / ||b|| (0 when b = 0)
  double seconds = 0;            // whole solve() call
  std::string solver_description;
};

class ElasticModel {
 public:
  // `mesh` is referenced, not copied: it must outlive the model and be
  // identical on every rank. `fixed_nodes` (unique, in range, same on every
  // rank) are the Dirichlet nodes; they must not all be collinear, otherwise
  // rigid rotations stay free and the system is singular.
  ElasticModel(MPI_Comm comm, const TetMesh& mesh, std::vector<int> fixed_nodes,
               ElasticOptions options);
  ~ElasticModel();
  ElasticModel(const ElasticModel&) = delete;
  ElasticModel& operator=(const ElasticModel&) = delete;

  void assemble();
  void setup_solver();

  // `fixed_displacements_mm[i]` is the displacement of fixed_nodes[i]; it must
  // be given (identically) on every rank, like the mesh. The full field (one
  // vector per mesh node, fixed nodes included) is returned on EVERY rank: the
  // daemon needs it on rank 0 and an allgather of 3N doubles is cheap next to
  // the solve. Throws ComputeError when the solver does not converge.
  SolveReport solve(const std::vector<Eigen::Vector3d>& fixed_displacements_mm,
                    std::vector<Eigen::Vector3d>& node_displacements_mm);
  // Same with nodal forces (Pa*mm^2, one per mesh node, e.g. from
  // consistent_nodal_loads); forces on fixed nodes are ignored (reactions).
  SolveReport solve(const std::vector<Eigen::Vector3d>& fixed_displacements_mm,
                    const std::vector<Eigen::Vector3d>& node_forces,
                    std::vector<Eigen::Vector3d>& node_displacements_mm);

  const PhaseTimes& times() const;
  // Numeric factorisations / preconditioner set-ups performed so far. Stays 1
  // after setup_solver() however many solves follow: new boundary values never
  // refactorise (checked against the factor's PETSc object state).
  int factorisation_count() const;
  // Node range [begin, end) owned by this rank.
  std::pair<int, int> owned_nodes() const;
  std::string solver_description() const;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

const char* to_string(DirichletMethod method);
const char* to_string(SolverKind solver);

}  // namespace brainshift
