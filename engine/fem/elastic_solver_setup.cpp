// Building the constrained system (A_ff/A_fb or the row-replaced matrix) and
// configuring KSP/PC for each SolverKind, once per model.
#include <cstdio>
#include <string>

// PetscObjectStateGet is documented public API but declared in this header.
#include <petsc/private/petscimpl.h>

#include "core/errors.h"
#include "fem/elastic_model_impl.h"
#include "fem/petsc_check.h"

namespace brainshift {

namespace {

IS block_index_set(MPI_Comm comm, const std::vector<PetscInt>& nodes) {
  IS is = nullptr;
  BS_PETSC(ISCreateBlock(comm, 3, static_cast<PetscInt>(nodes.size()), nodes.data(),
                         PETSC_COPY_VALUES, &is));
  return is;
}

// A_ff and A_fb are extracted once; every later boundary set costs one
// MatMult with A_fb. Block index sets keep block size 3 on the sub-matrices
// (GAMG's rigid-body near-null space and the bs-aware kernels rely on it).
void build_reduced(ElasticModel::Impl& m) {
  m.free_is = block_index_set(m.comm, m.owned_free);
  m.fixed_is = block_index_set(m.comm, m.owned_fixed);
  BS_PETSC(MatCreateSubMatrix(m.stiffness, m.free_is, m.free_is, MAT_INITIAL_MATRIX, &m.free_free));
  BS_PETSC(MatCreateSubMatrix(m.stiffness, m.free_is, m.fixed_is, MAT_INITIAL_MATRIX, &m.free_fixed));
  // Set explicitly: MUMPS picks its symmetric (LDL^T) path only when told.
  BS_PETSC(MatSetOption(m.free_free, MAT_SYMMETRIC, PETSC_TRUE));
  BS_PETSC(MatSetOption(m.free_free, MAT_SPD, PETSC_TRUE));
  BS_PETSC(MatCreateVecs(m.free_fixed, &m.boundary_values, nullptr));
  BS_PETSC(MatCreateVecs(m.free_free, &m.solution, &m.rhs));
}

// The published method: identity rows for the fixed dofs, value in the rhs.
// Columns stay, so the matrix is non-symmetric.
void build_row_replaced(ElasticModel::Impl& m) {
  BS_PETSC(MatDuplicate(m.stiffness, MAT_COPY_VALUES, &m.row_replaced));
  std::vector<PetscInt> rows;
  rows.reserve(3 * m.owned_fixed.size());
  for (PetscInt v : m.owned_fixed)
    for (PetscInt c = 0; c < 3; ++c) rows.push_back(3 * v + c);
  BS_PETSC(MatZeroRows(m.row_replaced, static_cast<PetscInt>(rows.size()), rows.data(), 1.0,
                       nullptr, nullptr));
  BS_PETSC(MatSetOption(m.row_replaced, MAT_SYMMETRIC, PETSC_FALSE));
  BS_PETSC(MatCreateVecs(m.row_replaced, &m.solution, &m.rhs));
}

void set_rigid_body_near_null_space(ElasticModel::Impl& m) {
  Vec coords = nullptr;
  BS_PETSC(VecDuplicate(m.solution, &coords));
  BS_PETSC(VecSetBlockSize(coords, 3));
  PetscScalar* a = nullptr;
  BS_PETSC(VecGetArray(coords, &a));
  for (std::size_t i = 0; i < m.owned_free.size(); ++i)
    for (int c = 0; c < 3; ++c) a[3 * i + c] = m.mesh->nodes_mm[m.owned_free[i]][c];
  BS_PETSC(VecRestoreArray(coords, &a));
  MatNullSpace near_null = nullptr;
  BS_PETSC(MatNullSpaceCreateRigidBody(coords, &near_null));
  BS_PETSC(MatSetNearNullSpace(m.free_free, near_null));
  BS_PETSC(MatNullSpaceDestroy(&near_null));
  BS_PETSC(VecDestroy(&coords));
}

// CHOLMOD is sequential: on >1 ranks "cholmod" gathers the whole system onto
// every rank (PCREDUNDANT) and factors it there; "mumps" factors distributed.
// With row replacement the factorisation is LU, and SuiteSparse's LU is UMFPACK.
void configure_direct(ElasticModel::Impl& m, PC pc) {
  const bool lu = !m.eliminates();
  const PCType factor_type = lu ? PCLU : PCCHOLESKY;
  std::string package = m.options.direct_package;
  if (package == "cholmod" && lu) package = "umfpack";
  PC factor_pc = pc;
  if (m.size > 1 && package != "mumps") {
    BS_PETSC(PCSetType(pc, PCREDUNDANT));
    BS_PETSC(PCRedundantSetNumber(pc, m.size));
    KSP inner = nullptr;
    BS_PETSC(PCRedundantGetKSP(pc, &inner));
    BS_PETSC(KSPGetPC(inner, &factor_pc));
    m.description = "redundant ";
  }
  BS_PETSC(PCSetType(factor_pc, factor_type));
  BS_PETSC(PCFactorSetMatSolverType(factor_pc, package.c_str()));
  m.description += std::string(factor_type) + "/" + package;
}

void configure_gmres_sub_solvers(ElasticModel::Impl& m, PC pc) {
  PetscBool is_bjacobi = PETSC_FALSE;
  BS_PETSC(PetscObjectTypeCompare(reinterpret_cast<PetscObject>(pc), PCBJACOBI, &is_bjacobi));
  if (!is_bjacobi) return;  // the user overrode -fem_pc_type
  PetscInt local_blocks = 0, first = 0;
  KSP* sub = nullptr;
  BS_PETSC(PCBJacobiGetSubKSP(pc, &local_blocks, &first, &sub));
  for (PetscInt b = 0; b < local_blocks; ++b) {
    PC sub_pc = nullptr;
    BS_PETSC(KSPGetPC(sub[b], &sub_pc));
    BS_PETSC(PCSetType(sub_pc, PCILU));
    BS_PETSC(PCFactorSetLevels(sub_pc, 0));
    // ILU(0) of this matrix broke down at nu = 0.49 without a shift (docs/DESIGN.md,
    // "Measured facts").
    BS_PETSC(PCFactorSetShiftType(sub_pc, MAT_SHIFT_POSITIVE_DEFINITE));
    BS_PETSC(KSPSetFromOptions(sub[b]));  // -fem_sub_* may still override
  }
  // Factor the blocks now, not inside the first solve.
  BS_PETSC(KSPSetUpOnBlocks(m.ksp));
}

std::string describe_iterative(const ElasticModel::Impl& m) {
  KSPType ksp_type = nullptr;
  PCType pc_type = nullptr;
  PC pc = nullptr;
  BS_PETSC(KSPGetType(m.ksp, &ksp_type));
  BS_PETSC(KSPGetPC(m.ksp, &pc));
  BS_PETSC(PCGetType(pc, &pc_type));
  char rtol[32];
  std::snprintf(rtol, sizeof rtol, "%.1e", m.options.rtol);
  return std::string(ksp_type) + "+" + pc_type + " rtol " + rtol;
}

void configure_ksp(ElasticModel::Impl& m) {
  Mat op = m.system_matrix();
  BS_PETSC(KSPCreate(m.comm, &m.ksp));
  BS_PETSC(KSPSetOptionsPrefix(m.ksp, "fem_"));
  BS_PETSC(KSPSetOperators(m.ksp, op, op));
  // The operator never changes after set-up; never let PETSc redo the PC.
  BS_PETSC(KSPSetReusePreconditioner(m.ksp, PETSC_TRUE));
  BS_PETSC(KSPSetTolerances(m.ksp, m.options.rtol, PETSC_DEFAULT, PETSC_DEFAULT,
                            m.options.max_iterations));
  PC pc = nullptr;
  BS_PETSC(KSPGetPC(m.ksp, &pc));
  switch (m.options.solver) {
    case SolverKind::direct_cholesky:
      BS_PETSC(KSPSetType(m.ksp, KSPPREONLY));
      configure_direct(m, pc);
      break;
    case SolverKind::cg_gamg:
      BS_PETSC(KSPSetType(m.ksp, KSPCG));
      BS_PETSC(PCSetType(pc, PCGAMG));
      set_rigid_body_near_null_space(m);
      BS_PETSC(KSPSetInitialGuessNonzero(m.ksp, PETSC_TRUE));  // warm start
      // rtol then bounds the true residual, not the preconditioned one.
      BS_PETSC(KSPSetNormType(m.ksp, KSP_NORM_UNPRECONDITIONED));
      break;
    case SolverKind::gmres_bjacobi:
      BS_PETSC(KSPSetType(m.ksp, KSPGMRES));
      // Restart 30 (the default) stalls on nearly incompressible tissue.
      BS_PETSC(KSPGMRESSetRestart(m.ksp, 100));
      BS_PETSC(PCSetType(pc, PCBJACOBI));
      // Right preconditioning: GMRES then minimises the true residual and rtol means it.
      BS_PETSC(KSPSetPCSide(m.ksp, PC_RIGHT));
      BS_PETSC(KSPSetInitialGuessNonzero(m.ksp, PETSC_TRUE));
      break;
  }
  BS_PETSC(KSPSetFromOptions(m.ksp));
  BS_PETSC(KSPSetUp(m.ksp));
  if (m.options.solver == SolverKind::gmres_bjacobi) configure_gmres_sub_solvers(m, pc);
  if (m.options.solver != SolverKind::direct_cholesky) m.description = describe_iterative(m);
  m.description += std::string(", ") + to_string(m.options.dirichlet);
}

// The factored matrix of a direct solve (inside PCREDUNDANT if used), or null.
Mat find_factor(KSP ksp) {
  PC pc = nullptr;
  BS_PETSC(KSPGetPC(ksp, &pc));
  PetscBool redundant = PETSC_FALSE, factor = PETSC_FALSE;
  BS_PETSC(PetscObjectTypeCompare(reinterpret_cast<PetscObject>(pc), PCREDUNDANT, &redundant));
  if (redundant) {
    KSP inner = nullptr;
    BS_PETSC(PCRedundantGetKSP(pc, &inner));
    return find_factor(inner);
  }
  BS_PETSC(PetscObjectTypeCompareAny(reinterpret_cast<PetscObject>(pc), &factor, PCLU, PCCHOLESKY, ""));
  if (!factor) return nullptr;
  Mat f = nullptr;
  BS_PETSC(PCFactorGetMatrix(pc, &f));
  return f;
}

}  // namespace

void build_constrained_system(ElasticModel::Impl& m) {
  if (m.eliminates())
    build_reduced(m);
  else
    build_row_replaced(m);
  BS_PETSC(VecDuplicate(m.rhs, &m.work));
  BS_PETSC(VecSet(m.solution, 0.0));  // first warm start from zero
}

// User options go into a private database that is active only while the
// solver is configured, so one model's -fem_* options never leak into another.
void configure_solver(ElasticModel::Impl& m) {
  PetscOptions private_options = nullptr;
  BS_PETSC(PetscOptionsCreate(&private_options));
  PetscErrorCode inserted = PetscOptionsInsertString(private_options, m.options.petsc_options.c_str());
  if (inserted != 0) {
    PetscOptionsDestroy(&private_options);
    throw InputError("ElasticOptions.petsc_options could not be parsed: \"" +
                     m.options.petsc_options + "\"");
  }
  BS_PETSC(PetscOptionsPush(private_options));
  try {
    configure_ksp(m);
  } catch (...) {
    PetscOptionsPop();
    PetscOptionsDestroy(&private_options);
    throw;
  }
  BS_PETSC(PetscOptionsPop());
  BS_PETSC(PetscOptionsDestroy(&private_options));
  PCFailedReason failed = PC_NOERROR;
  PC pc = nullptr;
  BS_PETSC(KSPGetPC(m.ksp, &pc));
  BS_PETSC(PCGetFailedReason(pc, &failed));
  if (failed != PC_NOERROR)
    throw ComputeError("elastic solver set-up failed (" + m.description + "): " +
                       PCFailedReasons[failed]);
  m.factor = find_factor(m.ksp);
  if (m.factor) BS_PETSC(PetscObjectStateGet(reinterpret_cast<PetscObject>(m.factor), &m.factor_state));
  m.factorisations = 1;
}

void track_factorisations(ElasticModel::Impl& m) {
  if (!m.factor) return;
  PetscObjectState now = 0;
  BS_PETSC(PetscObjectStateGet(reinterpret_cast<PetscObject>(m.factor), &now));
  if (now != m.factor_state) ++m.factorisations;
  m.factor_state = now;
}

}  // namespace brainshift
