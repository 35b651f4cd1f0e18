#pragma once
// The elastic model as it lives on every MPI rank: the same mesh, the same
// fixed nodes, each rank its share of the matrix and of the factorisation.
// Rank 0 drives it (load/solve broadcast a command first); workers answer the
// same commands from run_worker_loop.
#include <mpi.h>

#include <memory>
#include <string>
#include <vector>

#include "core/tet_mesh.h"
#include "fem/elastic_model.h"
#include "pipeline/fault_injection.h"

namespace brainshift {

class FemCluster {
 public:
  // Reads the fault-injection switch now, so a malformed one fails at start-up.
  explicit FemCluster(MPI_Comm comm);

  // Rank 0: broadcasts the load command and the data, then takes part.
  void drive_load(TetMesh mesh, std::vector<int> fixed_nodes, const ElasticOptions& options);
  SolveReport drive_solve(std::vector<Eigen::Vector3d> fixed_values_mm,
                          std::vector<Eigen::Vector3d>& node_displacements_mm);
  // Workers: the matching halves, after receive_command returned load/solve.
  void serve_load();
  void serve_solve();

  bool ready() const { return state_ != nullptr; }
  const ElasticModel& model() const { return *state_->model; }
  const TetMesh& mesh() const { return state_->mesh; }
  const std::vector<int>& fixed_nodes() const { return state_->fixed_nodes; }

 private:
  // Collective on every rank once the payload is known.
  void build(TetMesh mesh, std::vector<int> fixed_nodes, const ElasticOptions& options);
  SolveReport solve(const std::vector<Eigen::Vector3d>& values, std::vector<Eigen::Vector3d>& out);

  struct Loaded {
    TetMesh mesh;  // the model keeps a reference: must outlive it
    std::vector<int> fixed_nodes;
    std::unique_ptr<ElasticModel> model;
  };
  MPI_Comm comm_;
  int rank_ = 0;
  FaultPoint solve_fault_{"solve"};  // BRAINSHIFT_INJECT_FAULT, see fault_injection.h
  // Replaced only when a new load succeeded on every rank, so a failed
  // preop.load leaves the previous warm model serving.
  std::unique_ptr<Loaded> state_;
};

}  // namespace brainshift
