#include "fem/elastic_model.h"

#include <algorithm>
#include <stdexcept>

#include "core/errors.h"
#include "core/timer.h"
#include "fem/elastic_model_impl.h"
#include "fem/petsc_check.h"
#include "fem/petsc_session.h"

namespace brainshift {

namespace {

void validate_mesh(const TetMesh& mesh) {
  if (mesh.node_count() == 0 || mesh.tet_count() == 0)
    throw InputError("ElasticModel: the mesh has no nodes or no tetrahedra");
  if (mesh.tet_labels.size() != mesh.tet_count())
    throw InputError("ElasticModel: mesh has " + std::to_string(mesh.tet_labels.size()) +
                     " tet labels for " + std::to_string(mesh.tet_count()) + " tets");
  const int n = static_cast<int>(mesh.node_count());
  for (const auto& tet : mesh.tets)
    for (int v : tet)
      if (v < 0 || v >= n)
        throw InputError("ElasticModel: tet references node " + std::to_string(v) +
                         " outside [0, " + std::to_string(n) + ")");
}

// Fixed nodes that are all (nearly) on one line leave a rigid rotation about
// that line unconstrained: the stiffness restricted to the free dofs is singular.
void validate_fixed_nodes(const TetMesh& mesh, const std::vector<int>& fixed,
                          std::vector<int>& slot_of_node) {
  const int n = static_cast<int>(mesh.node_count());
  slot_of_node.assign(n, -1);
  for (std::size_t i = 0; i < fixed.size(); ++i) {
    const int v = fixed[i];
    if (v < 0 || v >= n)
      throw InputError("ElasticModel: fixed node " + std::to_string(v) + " out of range");
    if (slot_of_node[v] != -1)
      throw InputError("ElasticModel: fixed node " + std::to_string(v) + " listed twice");
    slot_of_node[v] = static_cast<int>(i);
  }
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (int v : fixed) mean += mesh.nodes_mm[v];
  mean /= std::max<std::size_t>(fixed.size(), 1);
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (int v : fixed) scatter += (mesh.nodes_mm[v] - mean) * (mesh.nodes_mm[v] - mean).transpose();
  const Eigen::Vector3d ev = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter).eigenvalues();
  if (fixed.size() < 3 || !(ev[1] > 1e-10 * ev[2]))
    throw InputError("ElasticModel: the " + std::to_string(fixed.size()) +
                     " fixed nodes are collinear: rigid rotations would stay unconstrained");
}

void validate_options(const ElasticOptions& o) {
  validate_material(o.default_material);
  for (const auto& [label, material] : o.material_by_label) validate_material(material);
  if (o.direct_package != "cholmod" && o.direct_package != "mumps")
    throw InputError("ElasticOptions.direct_package must be \"cholmod\" or \"mumps\", got \"" +
                     o.direct_package + "\"");
  if (o.dirichlet == DirichletMethod::row_replacement && o.solver == SolverKind::cg_gamg)
    throw InputError("ElasticOptions: cg_gamg needs a symmetric matrix; row_replacement makes "
                     "it non-symmetric (use symmetric_elimination, or gmres_bjacobi)");
  if (!(o.rtol > 0.0 && o.rtol < 1.0) || o.max_iterations < 1)
    throw InputError("ElasticOptions: rtol must be in (0, 1) and max_iterations >= 1");
}

// Elasticity matrices per label, computed once; label -> D, default for the rest.
class ElasticityByLabel {
 public:
  explicit ElasticityByLabel(const ElasticOptions& o) : fallback_(elasticity_matrix(o.default_material)) {
    for (const auto& [label, material] : o.material_by_label) by_label_[label] = elasticity_matrix(material);
  }
  const Eigen::Matrix<double, 6, 6>& operator()(int label) const {
    const auto it = by_label_.find(label);
    return it == by_label_.end() ? fallback_ : it->second;
  }

 private:
  Eigen::Matrix<double, 6, 6> fallback_;
  std::map<int, Eigen::Matrix<double, 6, 6>> by_label_;
};

// Exact block-row preallocation from the node graph: for each owned node the
// number of distinct neighbour nodes (itself included) inside / outside the
// owned range. Over-allocation wastes memory; under-allocation makes
// MatSetValues reallocate, which is orders of magnitude slower.
void preallocate(ElasticModel::Impl& m) {
  const PetscInt owned = m.node_end - m.node_begin;
  std::vector<std::vector<PetscInt>> neighbours(owned);
  for (const auto& tet : m.mesh->tets)
    for (int a : tet)
      if (a >= m.node_begin && a < m.node_end)
        for (int b : tet) neighbours[a - m.node_begin].push_back(b);
  std::vector<PetscInt> diagonal(owned), off_diagonal(owned);
  for (PetscInt i = 0; i < owned; ++i) {
    auto& list = neighbours[i];
    std::sort(list.begin(), list.end());
    list.erase(std::unique(list.begin(), list.end()), list.end());
    diagonal[i] = std::count_if(list.begin(), list.end(), [&](PetscInt b) {
      return b >= m.node_begin && b < m.node_end;
    });
    // An isolated node (in no tet) still needs its diagonal block.
    if (list.empty()) diagonal[i] = 1;
    off_diagonal[i] = static_cast<PetscInt>(list.size()) - diagonal[i];
    if (list.empty()) off_diagonal[i] = 0;
  }
  BS_PETSC(MatXAIJSetPreallocation(m.stiffness, 3, diagonal.data(), off_diagonal.data(), nullptr,
                                   nullptr));
}

void create_layout_and_matrix(ElasticModel::Impl& m) {
  const PetscInt dofs = 3 * static_cast<PetscInt>(m.mesh->node_count());
  PetscLayout layout = nullptr;
  BS_PETSC(PetscLayoutCreate(m.comm, &layout));
  BS_PETSC(PetscLayoutSetBlockSize(layout, 3));
  BS_PETSC(PetscLayoutSetSize(layout, dofs));
  BS_PETSC(PetscLayoutSetUp(layout));
  PetscInt row_begin = 0, row_end = 0;
  BS_PETSC(PetscLayoutGetRange(layout, &row_begin, &row_end));
  BS_PETSC(PetscLayoutDestroy(&layout));
  m.node_begin = row_begin / 3;
  m.node_end = row_end / 3;
  for (PetscInt v = m.node_begin; v < m.node_end; ++v)
    (m.fixed_slot[v] >= 0 ? m.owned_fixed : m.owned_free).push_back(v);

  BS_PETSC(MatCreate(m.comm, &m.stiffness));
  BS_PETSC(MatSetSizes(m.stiffness, row_end - row_begin, row_end - row_begin, dofs, dofs));
  BS_PETSC(MatSetBlockSize(m.stiffness, 3));
  BS_PETSC(MatSetType(m.stiffness, MATAIJ));
  preallocate(m);
  BS_PETSC(MatSetOption(m.stiffness, MAT_NEW_NONZERO_ALLOCATION_ERR, PETSC_TRUE));
}

void fill_owned(const ElasticModel::Impl& m, Vec v, const std::vector<PetscInt>& nodes,
                const std::vector<Eigen::Vector3d>& values, bool by_fixed_slot) {
  PetscScalar* a = nullptr;
  BS_PETSC(VecGetArray(v, &a));
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    const Eigen::Vector3d& x = values[by_fixed_slot ? m.fixed_slot[nodes[i]] : nodes[i]];
    for (int c = 0; c < 3; ++c) a[3 * i + c] = x[c];
  }
  BS_PETSC(VecRestoreArray(v, &a));
}

}  // namespace

ElasticModel::Impl::~Impl() {
  // Destructors cannot throw; PETSc destroy calls only fail on corrupt objects.
  KSPDestroy(&ksp);
  VecScatterDestroy(&to_all);
  for (Vec* v : {&boundary_values, &rhs, &solution, &work, &full_field, &all_field}) VecDestroy(v);
  ISDestroy(&free_is);
  ISDestroy(&fixed_is);
  for (Mat* a : {&stiffness, &free_free, &free_fixed, &row_replaced}) MatDestroy(a);
}

ElasticModel::ElasticModel(MPI_Comm comm, const TetMesh& mesh, std::vector<int> fixed_nodes,
                           ElasticOptions options)
    : impl_(std::make_unique<Impl>()) {
  if (!PetscSession::active())
    throw std::logic_error("ElasticModel needs a live PetscSession (PETSc not initialised)");
  Stopwatch clock;
  Impl& m = *impl_;
  validate_mesh(mesh);
  validate_options(options);
  validate_fixed_nodes(mesh, fixed_nodes, m.fixed_slot);
  m.comm = comm;
  MPI_Comm_rank(comm, &m.rank);
  MPI_Comm_size(comm, &m.size);
  m.mesh = &mesh;
  m.fixed_nodes = std::move(fixed_nodes);
  m.options = std::move(options);
  create_layout_and_matrix(m);
  m.times.create = clock.seconds();
}

ElasticModel::~ElasticModel() = default;

void ElasticModel::assemble() {
  Impl& m = *impl_;
  if (m.assembled) throw std::logic_error("ElasticModel::assemble called twice");
  Stopwatch clock;
  const TetMesh& mesh = *m.mesh;
  Eigen::Matrix<double, 12, 12, Eigen::RowMajor> ke, ke_sorted;  // PETSc reads values row-major
  const ElasticityByLabel elasticity(m.options);
  std::string bad_tet;  // first invalid tet on this rank
  for (std::size_t t = 0; t < mesh.tet_count() && bad_tet.empty(); ++t) {
    const auto& tet = mesh.tets[t];
    const int lowest = *std::min_element(tet.begin(), tet.end());
    if (lowest < m.node_begin || lowest >= m.node_end) continue;  // another rank's tet
    const std::array<Eigen::Vector3d, 4> x{mesh.nodes_mm[tet[0]], mesh.nodes_mm[tet[1]],
                                           mesh.nodes_mm[tet[2]], mesh.nodes_mm[tet[3]]};
    try {
      ke = p1_element_stiffness(x, elasticity(mesh.tet_labels[t]));
    } catch (const InputError& e) {
      bad_tet = "tet " + std::to_string(t) + ": " + e.what();
      break;
    }
    // Inserting with increasing column indices lets PETSc's AIJ row search
    // continue where the previous column was found instead of restarting.
    std::array<int, 4> order{0, 1, 2, 3};
    std::sort(order.begin(), order.end(), [&tet](int a, int b) { return tet[a] < tet[b]; });
    PetscInt blocks[4];
    for (int a = 0; a < 4; ++a) {
      blocks[a] = tet[order[a]];
      for (int b = 0; b < 4; ++b)
        ke_sorted.block<3, 3>(3 * a, 3 * b) = ke.block<3, 3>(3 * order[a], 3 * order[b]);
    }
    BS_PETSC(MatSetValuesBlocked(m.stiffness, 4, blocks, 4, blocks, ke_sorted.data(), ADD_VALUES));
  }
  // A rank that threw alone would leave the others hanging in MatAssemblyEnd:
  // agree on failure first, then every rank throws.
  int any_bad = bad_tet.empty() ? 0 : 1;
  MPI_Allreduce(MPI_IN_PLACE, &any_bad, 1, MPI_INT, MPI_MAX, m.comm);
  if (any_bad)
    throw InputError("ElasticModel::assemble: " +
                     (bad_tet.empty() ? std::string("invalid tet on another rank") : bad_tet));
  BS_PETSC(MatAssemblyBegin(m.stiffness, MAT_FINAL_ASSEMBLY));
  BS_PETSC(MatAssemblyEnd(m.stiffness, MAT_FINAL_ASSEMBLY));
  BS_PETSC(MatSetOption(m.stiffness, MAT_SYMMETRIC, PETSC_TRUE));
  m.assembled = true;
  m.times.assemble = clock.seconds();
}

void ElasticModel::setup_solver() {
  Impl& m = *impl_;
  if (!m.assembled) throw std::logic_error("ElasticModel::setup_solver before assemble");
  if (m.solver_ready) throw std::logic_error("ElasticModel::setup_solver called twice");
  Stopwatch clock;
  build_constrained_system(m);
  configure_solver(m);
  BS_PETSC(MatCreateVecs(m.stiffness, &m.full_field, nullptr));
  BS_PETSC(VecScatterCreateToAll(m.full_field, &m.to_all, &m.all_field));
  // With elimination every solve uses only A_ff and A_fb (copies): the full K
  // (~70 MB at the default mesh, per system) is not kept in the warm state.
  if (m.eliminates()) BS_PETSC(MatDestroy(&m.stiffness));
  m.solver_ready = true;
  m.times.setup = clock.seconds();
}

SolveReport ElasticModel::solve(const std::vector<Eigen::Vector3d>& fixed_displacements_mm,
                                std::vector<Eigen::Vector3d>& node_displacements_mm) {
  return solve(fixed_displacements_mm,
               std::vector<Eigen::Vector3d>(impl_->mesh->node_count(), Eigen::Vector3d::Zero()),
               node_displacements_mm);
}

namespace {

// rhs = f_f - A_fb u_b (elimination) or f with fixed rows = value (row replacement).
void form_rhs(ElasticModel::Impl& m, const std::vector<Eigen::Vector3d>& values,
              const std::vector<Eigen::Vector3d>& forces) {
  if (m.eliminates()) {
    fill_owned(m, m.boundary_values, m.owned_fixed, values, true);
    fill_owned(m, m.rhs, m.owned_free, forces, false);
    BS_PETSC(MatMult(m.free_fixed, m.boundary_values, m.work));
    BS_PETSC(VecAXPY(m.rhs, -1.0, m.work));
    return;
  }
  PetscScalar* a = nullptr;
  BS_PETSC(VecGetArray(m.rhs, &a));
  for (PetscInt v = m.node_begin; v < m.node_end; ++v) {
    const int slot = m.fixed_slot[v];
    const Eigen::Vector3d& x = slot >= 0 ? values[slot] : forces[v];
    for (int c = 0; c < 3; ++c) a[3 * (v - m.node_begin) + c] = x[c];
  }
  BS_PETSC(VecRestoreArray(m.rhs, &a));
}

void check_converged(const ElasticModel::Impl& m) {
  KSPConvergedReason reason;
  BS_PETSC(KSPGetConvergedReason(m.ksp, &reason));
  if (reason >= 0) return;
  PetscInt its = 0;
  BS_PETSC(KSPGetIterationNumber(m.ksp, &its));
  throw ComputeError("elastic solve did not converge: " + std::string(KSPConvergedReasons[reason]) +
                     " after " + std::to_string(its) + " iterations (" + m.description + ")");
}

// Merges free and fixed dofs into the distributed full field, then replicates it.
void gather_field(ElasticModel::Impl& m, std::vector<Eigen::Vector3d>& out) {
  if (m.eliminates()) {
    const PetscScalar *free = nullptr, *fixed = nullptr;
    PetscScalar* full = nullptr;
    BS_PETSC(VecGetArrayRead(m.solution, &free));
    BS_PETSC(VecGetArrayRead(m.boundary_values, &fixed));
    BS_PETSC(VecGetArray(m.full_field, &full));
    std::size_t next_free = 0, next_fixed = 0;
    for (PetscInt v = m.node_begin; v < m.node_end; ++v) {
      const PetscScalar* src = m.fixed_slot[v] >= 0 ? fixed + 3 * next_fixed++ : free + 3 * next_free++;
      std::copy(src, src + 3, full + 3 * (v - m.node_begin));
    }
    BS_PETSC(VecRestoreArray(m.full_field, &full));
    BS_PETSC(VecRestoreArrayRead(m.boundary_values, &fixed));
    BS_PETSC(VecRestoreArrayRead(m.solution, &free));
  } else {
    BS_PETSC(VecCopy(m.solution, m.full_field));
  }
  BS_PETSC(VecScatterBegin(m.to_all, m.full_field, m.all_field, INSERT_VALUES, SCATTER_FORWARD));
  BS_PETSC(VecScatterEnd(m.to_all, m.full_field, m.all_field, INSERT_VALUES, SCATTER_FORWARD));
  const PetscScalar* all = nullptr;
  BS_PETSC(VecGetArrayRead(m.all_field, &all));
  out.resize(m.mesh->node_count());
  for (std::size_t v = 0; v < out.size(); ++v) out[v] = Eigen::Vector3d(all + 3 * v);
  BS_PETSC(VecRestoreArrayRead(m.all_field, &all));
}

}  // namespace

SolveReport ElasticModel::solve(const std::vector<Eigen::Vector3d>& fixed_displacements_mm,
                                const std::vector<Eigen::Vector3d>& node_forces,
                                std::vector<Eigen::Vector3d>& node_displacements_mm) {
  Impl& m = *impl_;
  if (!m.solver_ready) throw std::logic_error("ElasticModel::solve before setup_solver");
  if (fixed_displacements_mm.size() != m.fixed_nodes.size())
    throw InputError("ElasticModel::solve: " + std::to_string(fixed_displacements_mm.size()) +
                     " displacements for " + std::to_string(m.fixed_nodes.size()) + " fixed nodes");
  if (node_forces.size() != m.mesh->node_count())
    throw InputError("ElasticModel::solve: " + std::to_string(node_forces.size()) +
                     " nodal forces for " + std::to_string(m.mesh->node_count()) + " nodes");
  Stopwatch total, clock;
  form_rhs(m, fixed_displacements_mm, node_forces);
  m.times.boundary = clock.lap();
  BS_PETSC(KSPSolve(m.ksp, m.rhs, m.solution));
  m.times.solve = clock.lap();
  track_factorisations(m);
  check_converged(m);

  SolveReport report;
  PetscInt its = 0;
  BS_PETSC(KSPGetIterationNumber(m.ksp, &its));
  report.iterations = static_cast<int>(its);
  // True residual of the solved system (not the preconditioned estimate).
  PetscReal rhs_norm = 0;
  BS_PETSC(MatMult(m.system_matrix(), m.solution, m.work));
  BS_PETSC(VecAYPX(m.work, -1.0, m.rhs));
  BS_PETSC(VecNorm(m.work, NORM_2, &report.residual_norm));
  BS_PETSC(VecNorm(m.rhs, NORM_2, &rhs_norm));
  report.relative_residual = rhs_norm > 0 ? report.residual_norm / rhs_norm : 0.0;
  gather_field(m, node_displacements_mm);
  m.times.gather = clock.lap();
  report.seconds = total.seconds();
  report.solver_description = m.description;
  return report;
}

const PhaseTimes& ElasticModel::times() const { return impl_->times; }
int ElasticModel::factorisation_count() const { return impl_->factorisations; }
std::pair<int, int> ElasticModel::owned_nodes() const {
  return {static_cast<int>(impl_->node_begin), static_cast<int>(impl_->node_end)};
}
std::string ElasticModel::solver_description() const { return impl_->description; }

const char* to_string(DirichletMethod method) {
  return method == DirichletMethod::symmetric_elimination ? "symmetric elimination"
                                                          : "row replacement";
}

const char* to_string(SolverKind solver) {
  switch (solver) {
    case SolverKind::direct_cholesky: return "direct";
    case SolverKind::cg_gamg: return "CG + GAMG";
    case SolverKind::gmres_bjacobi: return "GMRES + block Jacobi/ILU(0)";
  }
  return "unknown";
}

}  // namespace brainshift
