#pragma once
// The elastic model as it lives on every MPI rank: the same mesh, the same
// fixed nodes, each rank its share of the matrix and of the factorisation.
// One mesh can carry several systems that differ only in their fixed nodes
// (system 0: the brain surface and cavity walls; system 1 and on: the same
// plus the wall of a resectable structure), each factorised once.
// Rank 0 drives it (load/solve broadcast a command first); workers answer the
// same commands from run_worker_loop.
#include <mpi.h>

#include <memory>
#include <string>
#include <vector>

#include "core/tet_mesh.h"
#include "fem/elastic_model.h"
#include "core/fault_injection.h"

namespace brainshift {

class FemCluster {
 public:
  // Reads the fault-injection switch now, so a malformed one fails at start-up.
  explicit FemCluster(MPI_Comm comm);

  // Rank 0: broadcasts the load command and the data, then takes part.
  void drive_load(TetMesh mesh, std::vector<std::vector<int>> fixed_node_sets, const ElasticOptions& options);
  // fixed_values_mm follows fixed_nodes(system).
  SolveReport drive_solve(std::vector<Eigen::Vector3d> fixed_values_mm,
                          std::vector<Eigen::Vector3d>& node_displacements_mm, int system = 0);
  // Workers: the matching halves, after receive_command returned load/solve.
  void serve_load();
  void serve_solve();

  bool ready() const { return state_ != nullptr; }
  int system_count() const { return state_ ? static_cast<int>(state_->systems.size()) : 0; }
  const ElasticModel& model(int system = 0) const { return *state_->systems.at(system).model; }
  const TetMesh& mesh() const { return state_->mesh; }
  const std::vector<int>& fixed_nodes(int system = 0) const { return state_->systems.at(system).fixed_nodes; }

 private:
  // Collective on every rank once the payload is known.
  void build(TetMesh mesh, std::vector<std::vector<int>> fixed_node_sets, const ElasticOptions& options);
  SolveReport solve(int system, const std::vector<Eigen::Vector3d>& values, std::vector<Eigen::Vector3d>& out);

  struct System {
    std::vector<int> fixed_nodes;
    std::unique_ptr<ElasticModel> model;
  };
  struct Loaded {
    TetMesh mesh;  // the models keep a reference: must outlive them
    std::vector<System> systems;
  };
  MPI_Comm comm_;
  int rank_ = 0;
  FaultPoint solve_fault_{"solve"};  // BRAINSHIFT_INJECT_FAULT, see fault_injection.h
  // Replaced only when a new load succeeded on every rank, so a failed
  // preop.load leaves the previous warm model serving.
  std::unique_ptr<Loaded> state_;
};

}  // namespace brainshift
