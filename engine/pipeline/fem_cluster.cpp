#include "pipeline/fem_cluster.h"

#include "core/errors.h"
#include "pipeline/mpi_commands.h"

namespace brainshift {

using mpi_channel::Command;

FemCluster::FemCluster(MPI_Comm comm) : comm_(comm) {
  MPI_Comm_rank(comm_, &rank_);
  (void)injected_fault();
}

namespace {

void broadcast_sets(MPI_Comm comm, std::vector<std::vector<int>>& sets) {
  std::vector<int> count{static_cast<int>(sets.size())};
  mpi_channel::broadcast(comm, count);
  sets.resize(static_cast<std::size_t>(count.at(0)));
  for (auto& set : sets) mpi_channel::broadcast(comm, set);
}

}  // namespace

void FemCluster::drive_load(TetMesh mesh, std::vector<std::vector<int>> fixed_node_sets,
                            const ElasticOptions& options) {
  if (fixed_node_sets.empty()) throw ComputeError("elastic model needs at least one set of fixed nodes");
  mpi_channel::broadcast_command(comm_, Command::load);
  std::string options_json = mpi_channel::elastic_options_to_json(options);
  mpi_channel::broadcast(comm_, mesh);
  broadcast_sets(comm_, fixed_node_sets);
  mpi_channel::broadcast(comm_, options_json);
  build(std::move(mesh), std::move(fixed_node_sets), options);
}

void FemCluster::serve_load() {
  TetMesh mesh;
  std::vector<std::vector<int>> fixed_node_sets;
  std::string options_json;
  mpi_channel::broadcast(comm_, mesh);
  broadcast_sets(comm_, fixed_node_sets);
  mpi_channel::broadcast(comm_, options_json);
  try {
    build(std::move(mesh), std::move(fixed_node_sets), mpi_channel::elastic_options_from_json(options_json));
  } catch (const std::exception&) {
    // Rank 0 reports the failure; the worker just drops its state.
  }
}

void FemCluster::build(TetMesh mesh, std::vector<std::vector<int>> fixed_node_sets, const ElasticOptions& options) {
  auto next = std::make_unique<Loaded>();
  next->mesh = std::move(mesh);
  next->systems.resize(fixed_node_sets.size());
  std::string message;
  bool ok = true;
  try {
    for (std::size_t i = 0; i < fixed_node_sets.size(); ++i) {
      System& system = next->systems[i];
      system.fixed_nodes = std::move(fixed_node_sets[i]);
      system.model = std::make_unique<ElasticModel>(comm_, next->mesh, system.fixed_nodes, options);
      system.model->assemble();
      system.model->setup_solver();
    }
  } catch (const std::exception& e) {
    ok = false;
    message = e.what();
  }
  if (!mpi_channel::agree(comm_, ok, &message))
    throw ComputeError("elastic model set-up failed: " + message);
  state_ = std::move(next);
}

SolveReport FemCluster::drive_solve(std::vector<Eigen::Vector3d> fixed_values_mm,
                                    std::vector<Eigen::Vector3d>& node_displacements_mm, int system) {
  if (!state_) throw ComputeError("elastic model is not loaded");
  if (system < 0 || system >= system_count())
    throw ComputeError("elastic model has no system " + std::to_string(system));
  mpi_channel::broadcast_command(comm_, Command::solve);
  std::vector<int> which{system};
  mpi_channel::broadcast(comm_, which);
  mpi_channel::broadcast(comm_, fixed_values_mm);
  return solve(system, fixed_values_mm, node_displacements_mm);
}

void FemCluster::serve_solve() {
  std::vector<int> which;
  mpi_channel::broadcast(comm_, which);
  std::vector<Eigen::Vector3d> values;
  mpi_channel::broadcast(comm_, values);
  std::vector<Eigen::Vector3d> out;
  try {
    solve(which.empty() ? -1 : which.front(), values, out);
  } catch (const std::exception&) {
  }
}

SolveReport FemCluster::solve(int system, const std::vector<Eigen::Vector3d>& values,
                              std::vector<Eigen::Vector3d>& out) {
  // Two agreements: a rank that cannot take part must say so before the
  // collective KSPSolve, or the other ranks would wait in it for ever; and a
  // rank whose part of the solve failed says so after it.
  std::string message;
  bool ok = state_ != nullptr && system >= 0 && system < system_count();
  if (!ok) message = "elastic system " + std::to_string(system) + " is not loaded on rank " + std::to_string(rank_);
  if (ok && solve_fault_.fires(rank_)) {
    ok = false;
    message = "injected fault (BRAINSHIFT_INJECT_FAULT) on rank " + std::to_string(rank_);
  }
  if (!mpi_channel::agree(comm_, ok, &message)) throw ComputeError("elastic solve failed: " + message);
  SolveReport report;
  try {
    report = state_->systems[static_cast<std::size_t>(system)].model->solve(values, out);
  } catch (const std::exception& e) {
    ok = false;
    message = "rank " + std::to_string(rank_) + ": " + e.what();
  }
  if (!mpi_channel::agree(comm_, ok, &message)) throw ComputeError("elastic solve failed: " + message);
  return report;
}

}  // namespace brainshift
