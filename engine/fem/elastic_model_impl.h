#pragma once
// Internal to engine/fem: the PETSc state behind ElasticModel, shared by
// elastic_model.cpp (layout, assembly, solve) and elastic_solver_setup.cpp
// (building the constrained system and configuring KSP/PC).
#include <petscksp.h>

#include <string>
#include <vector>

#include "fem/elastic_model.h"

namespace brainshift {

struct ElasticModel::Impl {
  MPI_Comm comm = MPI_COMM_NULL;
  int rank = 0, size = 1;
  const TetMesh* mesh = nullptr;
  std::vector<int> fixed_nodes;  // as given by the caller (order of the values)
  std::vector<int> fixed_slot;   // per mesh node: index into fixed_nodes, or -1
  ElasticOptions options;

  PetscInt node_begin = 0, node_end = 0;  // owned node range (PETSc's split)
  std::vector<PetscInt> owned_free, owned_fixed;  // ascending node ids

  Mat stiffness = nullptr;      // full K, 3N x 3N, block size 3 (freed after set-up with elimination)
  Mat free_free = nullptr;      // A_ff (symmetric elimination)
  Mat free_fixed = nullptr;     // A_fb (symmetric elimination)
  Mat row_replaced = nullptr;   // K with fixed rows replaced by identity rows
  IS free_is = nullptr, fixed_is = nullptr;
  Vec boundary_values = nullptr;  // u_b, fixed-dof layout (elimination only)
  Vec rhs = nullptr, solution = nullptr, work = nullptr;  // layout of the solved system
  Vec full_field = nullptr, all_field = nullptr;          // all dofs; distributed / replicated
  VecScatter to_all = nullptr;
  KSP ksp = nullptr;
  Mat factor = nullptr;  // the factored matrix of a direct solve (not owned)
  PetscObjectState factor_state = 0;

  bool assembled = false, solver_ready = false;
  int factorisations = 0;
  std::string description;
  PhaseTimes times;

  ~Impl();
  bool eliminates() const { return options.dirichlet == DirichletMethod::symmetric_elimination; }
  Mat system_matrix() const { return eliminates() ? free_free : row_replaced; }
};

// elastic_solver_setup.cpp
void build_constrained_system(ElasticModel::Impl& m);
void configure_solver(ElasticModel::Impl& m);
// Re-reads the factor's object state; counts a refactorisation if it changed.
void track_factorisations(ElasticModel::Impl& m);

}  // namespace brainshift
