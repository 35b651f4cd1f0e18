#pragma once
// The small command channel between rank 0 and the worker ranks. Rank 0
// broadcasts a command code, then its payload; every collective step ends with
// an agreement (all ranks report success or failure) so no rank is left
// waiting in a collective that another rank abandoned.
#include <mpi.h>

#include <Eigen/Dense>
#include <string>
#include <vector>

#include "core/tet_mesh.h"
#include "fem/elastic_model.h"

namespace brainshift::mpi_channel {

enum class Command : int { stop = 0, load = 1, solve = 2 };

void broadcast_command(MPI_Comm comm, Command command);
Command receive_command(MPI_Comm comm);

// Payload broadcasts from rank 0 (root) to all; on workers the argument is
// overwritten.
void broadcast(MPI_Comm comm, std::string& text);
void broadcast(MPI_Comm comm, std::vector<int>& values);
void broadcast(MPI_Comm comm, std::vector<Eigen::Vector3d>& vectors);
void broadcast(MPI_Comm comm, TetMesh& mesh);

// Every rank says whether its part succeeded; returns true only when all did.
// The first failing rank's message is returned in *message on every rank.
bool agree(MPI_Comm comm, bool ok, std::string* message);

std::string elastic_options_to_json(const ElasticOptions& options);
ElasticOptions elastic_options_from_json(const std::string& text);

}  // namespace brainshift::mpi_channel
