#include "pipeline/fem_cluster.h"

#include "core/errors.h"
#include "pipeline/mpi_commands.h"

namespace brainshift {

using mpi_channel::Command;

FemCluster::FemCluster(MPI_Comm comm) : comm_(comm) {
  MPI_Comm_rank(comm_, &rank_);
  (void)injected_fault();
}

void FemCluster::drive_load(TetMesh mesh, std::vector<int> fixed_nodes, const ElasticOptions& options) {
  mpi_channel::broadcast_command(comm_, Command::load);
  std::string options_json = mpi_channel::elastic_options_to_json(options);
  mpi_channel::broadcast(comm_, mesh);
  mpi_channel::broadcast(comm_, fixed_nodes);
  mpi_channel::broadcast(comm_, options_json);
  build(std::move(mesh), std::move(fixed_nodes), options);
}

void FemCluster::serve_load() {
  TetMesh mesh;
  std::vector<int> fixed_nodes;
  std::string options_json;
  mpi_channel::broadcast(comm_, mesh);
  mpi_channel::broadcast(comm_, fixed_nodes);
  mpi_channel::broadcast(comm_, options_json);
  try {
    build(std::move(mesh), std::move(fixed_nodes), mpi_channel::elastic_options_from_json(options_json));
  } catch (const std::exception&) {
    // Rank 0 reports the failure; the worker just drops its state.
  }
}

void FemCluster::build(TetMesh mesh, std::vector<int> fixed_nodes, const ElasticOptions& options) {
  auto next = std::make_unique<Loaded>();
  next->mesh = std::move(mesh);
  next->fixed_nodes = std::move(fixed_nodes);
  std::string message;
  bool ok = true;
  try {
    next->model = std::make_unique<ElasticModel>(comm_, next->mesh, next->fixed_nodes, options);
    next->model->assemble();
    next->model->setup_solver();
  } catch (const std::exception& e) {
    ok = false;
    message = e.what();
  }
  if (!mpi_channel::agree(comm_, ok, &message))
    throw ComputeError("elastic model set-up failed: " + message);
  state_ = std::move(next);
}

SolveReport FemCluster::drive_solve(std::vector<Eigen::Vector3d> fixed_values_mm,
                                    std::vector<Eigen::Vector3d>& node_displacements_mm) {
  if (!state_) throw ComputeError("elastic model is not loaded");
  mpi_channel::broadcast_command(comm_, Command::solve);
  mpi_channel::broadcast(comm_, fixed_values_mm);
  return solve(fixed_values_mm, node_displacements_mm);
}

void FemCluster::serve_solve() {
  std::vector<Eigen::Vector3d> values;
  mpi_channel::broadcast(comm_, values);
  std::vector<Eigen::Vector3d> out;
  try {
    solve(values, out);
  } catch (const std::exception&) {
  }
}

SolveReport FemCluster::solve(const std::vector<Eigen::Vector3d>& values,
                              std::vector<Eigen::Vector3d>& out) {
  // Two agreements: a rank that cannot take part must say so before the
  // collective KSPSolve, or the other ranks would wait in it for ever; and a
  // rank whose part of the solve failed says so after it.
  std::string message;
  bool ok = state_ != nullptr;
  if (!ok) message = "elastic model is not loaded on rank " + std::to_string(rank_);
  if (ok && solve_fault_.fires(rank_)) {
    ok = false;
    message = "injected fault (BRAINSHIFT_INJECT_FAULT) on rank " + std::to_string(rank_);
  }
  if (!mpi_channel::agree(comm_, ok, &message)) throw ComputeError("elastic solve failed: " + message);
  SolveReport report;
  try {
    report = state_->model->solve(values, out);
  } catch (const std::exception& e) {
    ok = false;
    message = "rank " + std::to_string(rank_) + ": " + e.what();
  }
  if (!mpi_channel::agree(comm_, ok, &message)) throw ComputeError("elastic solve failed: " + message);
  return report;
}

}  // namespace brainshift
