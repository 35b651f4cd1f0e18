#pragma once
// Element quality of a TetMesh: what the FEM cares about (no inverted or flat
// tets; dihedral angles away from 0 and 180 deg bound the condition number).
#include <cstddef>

#include "core/tet_mesh.h"

namespace brainshift {

struct MeshQuality {
  std::size_t nodes = 0, tets = 0, boundary_faces = 0;
  std::size_t inverted_tets = 0;    // signed volume < 0
  std::size_t degenerate_tets = 0;  // |volume| < 1e-8 * longest_edge^3
  double min_dihedral_deg = 0, max_dihedral_deg = 0;
  double max_radius_edge_ratio = 0;  // circumradius / shortest edge (regular tet: 0.612)
  double min_volume_mm3 = 0, total_volume_mm3 = 0;
};

MeshQuality measure_quality(const TetMesh& mesh);

// The six dihedral angles (deg) of one tet, edge order (01,02,03,12,13,23).
std::array<double, 6> dihedral_angles_deg(const TetMesh& mesh, std::size_t tet);

}  // namespace brainshift
