#pragma once
// A pair of facing walls of one surface (mesh/surface_contacts.h finds them,
// registration/active_surface.h keeps them apart).
#include <vector>

#include <Eigen/Dense>

namespace brainshift {

struct ContactPair {
  int vertex = 0;           // the vertex a ray starts at
  int facing = 0;           // the vertex of the hit triangle nearest to the hit point
  Eigen::Vector3d direction_from_vertex = Eigen::Vector3d::Zero();  // unit, from vertex toward facing
  double gap_mm = 0;        // distance from the vertex to the hit point
};

using ContactPairs = std::vector<ContactPair>;

}  // namespace brainshift
