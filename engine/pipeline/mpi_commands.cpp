#include "pipeline/mpi_commands.h"

#include <chrono>
#include <thread>

#include <nlohmann/json.hpp>

#include "core/errors.h"

namespace brainshift::mpi_channel {
namespace {

constexpr int kRoot = 0;

void check(int rc, const char* what) {
  if (rc != MPI_SUCCESS) throw ComputeError(std::string("MPI failure in ") + what);
}

unsigned long long broadcast_size(MPI_Comm comm, std::size_t size) {
  unsigned long long n = size;
  check(MPI_Bcast(&n, 1, MPI_UNSIGNED_LONG_LONG, kRoot, comm), "broadcast size");
  return n;
}

template <class T>
void broadcast_pod_vector(MPI_Comm comm, std::vector<T>& values) {
  const auto n = broadcast_size(comm, values.size());
  values.resize(n);
  if (n == 0) return;
  // Meshes of a few hundred thousand nodes stay far below INT_MAX bytes.
  check(MPI_Bcast(values.data(), static_cast<int>(n * sizeof(T)), MPI_BYTE, kRoot, comm),
        "broadcast payload");
}

}  // namespace

// Commands travel by non-blocking broadcast (both sides: a non-blocking
// collective never matches a blocking one). Workers wait for the next command
// for minutes between scans; MPI's blocking wait would spin on a core that
// rank 0's threads use during a scan, so they poll with a short sleep instead
// (at most ~0.2 ms added per command).
void broadcast_command(MPI_Comm comm, Command command) {
  int code = static_cast<int>(command);
  MPI_Request request;
  check(MPI_Ibcast(&code, 1, MPI_INT, kRoot, comm, &request), "broadcast command");
  check(MPI_Wait(&request, MPI_STATUS_IGNORE), "broadcast command");
}

Command receive_command(MPI_Comm comm) {
  int code = 0;
  MPI_Request request;
  check(MPI_Ibcast(&code, 1, MPI_INT, kRoot, comm, &request), "receive command");
  for (int done = 0;;) {
    check(MPI_Test(&request, &done, MPI_STATUS_IGNORE), "receive command");
    if (done) break;
    std::this_thread::sleep_for(std::chrono::microseconds(200));
  }
  return static_cast<Command>(code);
}

void broadcast(MPI_Comm comm, std::string& text) {
  std::vector<char> bytes(text.begin(), text.end());
  broadcast_pod_vector(comm, bytes);
  text.assign(bytes.begin(), bytes.end());
}

void broadcast(MPI_Comm comm, std::vector<int>& values) { broadcast_pod_vector(comm, values); }

void broadcast(MPI_Comm comm, std::vector<Eigen::Vector3d>& vectors) {
  broadcast_pod_vector(comm, vectors);
}

void broadcast(MPI_Comm comm, TetMesh& mesh) {
  broadcast_pod_vector(comm, mesh.nodes_mm);
  broadcast_pod_vector(comm, mesh.tets);
  broadcast_pod_vector(comm, mesh.tet_labels);
  broadcast_pod_vector(comm, mesh.boundary_faces);
}

bool agree(MPI_Comm comm, bool ok, std::string* message) {
  int rank = 0;
  MPI_Comm_rank(comm, &rank);
  // The lowest failing rank speaks for all.
  int failing = ok ? INT32_MAX : rank;
  int first_failing = INT32_MAX;
  check(MPI_Allreduce(&failing, &first_failing, 1, MPI_INT, MPI_MIN, comm), "agree");
  if (first_failing == INT32_MAX) return true;
  std::string text = message ? *message : std::string();
  std::vector<char> bytes(text.begin(), text.end());
  unsigned long long n = bytes.size();
  check(MPI_Bcast(&n, 1, MPI_UNSIGNED_LONG_LONG, first_failing, comm), "agree size");
  bytes.resize(n);
  if (n) check(MPI_Bcast(bytes.data(), static_cast<int>(n), MPI_BYTE, first_failing, comm), "agree text");
  if (message) message->assign(bytes.begin(), bytes.end());
  return false;
}

std::string elastic_options_to_json(const ElasticOptions& o) {
  nlohmann::json j;
  nlohmann::json materials = nlohmann::json::array();
  for (const auto& [label, m] : o.material_by_label)
    materials.push_back({{"label", label}, {"E", m.youngs_modulus_pa}, {"nu", m.poisson_ratio}});
  j["materials"] = materials;
  j["default"] = {{"E", o.default_material.youngs_modulus_pa}, {"nu", o.default_material.poisson_ratio}};
  j["dirichlet"] = static_cast<int>(o.dirichlet);
  j["solver"] = static_cast<int>(o.solver);
  j["direct_package"] = o.direct_package;
  j["rtol"] = o.rtol;
  j["max_iterations"] = o.max_iterations;
  j["petsc_options"] = o.petsc_options;
  return j.dump();
}

ElasticOptions elastic_options_from_json(const std::string& text) {
  const auto j = nlohmann::json::parse(text);
  ElasticOptions o;
  for (const auto& m : j.at("materials"))
    o.material_by_label[m.at("label").get<int>()] = Material{m.at("E").get<double>(), m.at("nu").get<double>()};
  o.default_material = Material{j.at("default").at("E").get<double>(), j.at("default").at("nu").get<double>()};
  o.dirichlet = static_cast<DirichletMethod>(j.at("dirichlet").get<int>());
  o.solver = static_cast<SolverKind>(j.at("solver").get<int>());
  o.direct_package = j.at("direct_package").get<std::string>();
  o.rtol = j.at("rtol").get<double>();
  o.max_iterations = j.at("max_iterations").get<int>();
  o.petsc_options = j.at("petsc_options").get<std::string>();
  return o;
}

}  // namespace brainshift::mpi_channel
