#pragma once
// CGAL-free second half of meshing: turns the raw tissue tets handed out of
// CGAL into the canonical TetMesh (orientation, degenerate removal, labels,
// boundary faces, space-filling-curve order). Kept apart from label_mesher.cpp
// so that the CGAL translation unit stays the only slow one to compile.
#include <array>
#include <cstdint>
#include <vector>

#include "core/image.h"
#include "core/tet_mesh.h"

namespace brainshift {

struct RawBoundaryFacet {
  int tet;              // index into RawTetMesh::tets
  int opposite_local;   // 0..3: the tet vertex NOT on this face
  int neighbour_label;  // 0 = outside, else the cavity label
};

struct RawTetMesh {
  std::vector<Eigen::Vector3d> nodes_mm;  // world RAS+ mm, may include unused nodes
  std::vector<std::array<int, 4>> tets;   // any orientation
  std::vector<RawBoundaryFacet> boundary;
  // Per tet: the label of its interface subdomain, or -1 (material from the
  // voxel nearest the centroid). Empty = all -1.
  std::vector<int> forced_labels;
};

struct AssemblyOptions {
  std::vector<std::uint16_t> cavity_labels;
  // Labels meshed as their own subdomain: only tets of that subdomain carry
  // them (forced_labels); elsewhere they read as the default tissue label.
  std::vector<std::uint16_t> interface_labels;
  std::uint16_t default_tissue_label = 1;
  // A tet is degenerate when |volume| < this * (longest edge)^3 (a regular
  // tet has 0.118): such tets carry no stiffness and break the FEM.
  double degenerate_relative_volume = 1e-8;
  // Keep only the face-connected piece of largest volume.
  bool keep_largest_component = false;
};

struct AssemblyReport {
  std::size_t dropped_degenerate = 0;
  std::size_t dropped_island_tets = 0;
};

// `labels` supplies each tet's material label (voxel nearest its centroid).
TetMesh assemble_tet_mesh(RawTetMesh raw, const LabelImage& labels,
                          const AssemblyOptions& options, AssemblyReport* report = nullptr);

// Permutation new_from_old... returned as order[new] = old, sorting points along
// a 3-D Morton (Z-order) curve over their bounding box; ties keep input order.
std::vector<int> morton_order(const std::vector<Eigen::Vector3d>& points);

}  // namespace brainshift
