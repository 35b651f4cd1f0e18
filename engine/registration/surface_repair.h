#pragma once
// Local repair of a surface match. An active-surface match can go wrong in a
// few places while the rest of it is good: the two walls of a thin ventricular
// horn or a narrow sulcus pulled through each other, a vertex dragged onto a
// segmentation island, a fold where the target has a hole. Throwing the whole
// match away for that loses a good result; keeping the defect lets a crossed
// surface drive the FEM.
//
// Instead the unreliable vertices take their displacement from the reliable
// vertices AROUND THEM IN SPACE (not along the surface): a Gaussian-weighted
// mean of the displacements of reliable vertices within 3 sigma of the
// vertex's start position. Both walls of a thin structure then move with one
// smooth field, and a smooth field whose gradient stays below 1 maps distinct
// points to distinct points: the repaired walls cannot cross. A vertex with no
// reliable vertex within 3 sigma searches twice as far, up to
// max_search_mm, and keeps the affine (non-rigid displacement 0) beyond that.
//
// The pipeline's loop (pipeline/surface_stage.cpp) finds the defects (flipped
// triangles, crossing triangle pairs, large residuals), fills them grown by a
// ring per round, and checks again.
#include <cstddef>
#include <vector>

#include <Eigen/Dense>

#include "core/tet_mesh.h"

namespace brainshift {

struct SurfaceRepairParameters {
  bool enabled = true;
  // A vertex left farther than this from its target after the match is
  // unreliable (segmentation noise is about a voxel; 3 mm is three).
  double unreliable_residual_mm = 3.0;
  int rounds = 6;  // repair-and-check rounds, one more ring each
  // Surface components smaller than this (mm^2; 200 ~ a ball of 8 mm) are not
  // matched on their own: label specks and fragments of thin horns follow the
  // reliable surface around them.
  double min_component_area_mm2 = 200.0;
  // Width of the spatial mean that repaired vertices take: wider than the
  // thinnest structures (horns, sulci: 1-3 mm), narrower than brain shift's
  // own variation (centimetres).
  double smoothing_mm = 2.5;
  double max_search_mm = 30.0;
};

// A surface motion that keeps every triangle oriented: no triangle's normal
// turns by more than max_normal_turn_deg from the start surface, and none
// shrinks below min_area_ratio of its start area (docs/DESIGN.md, "Quality
// gates": why 75 degrees and 0.1).
struct FoldGuard {
  double max_normal_turn_deg = 75.0;
  double min_area_ratio = 0.1;
};

// Vertex neighbours through triangle edges (sorted, unique).
std::vector<std::vector<int>> surface_vertex_neighbours(const TriSurface& surface);

// Adds `rings` rings of neighbours to the marked vertices.
void grow_marked(std::vector<char>& marked, const std::vector<std::vector<int>>& neighbours, int rings);

// Replaces the displacement of every marked vertex by the spatial mean of the
// unmarked ones (see above). positions: the start positions (mm). Returns the
// number of marked vertices that found no reliable vertex within max_search_mm.
std::size_t fill_from_reliable_neighbours(const std::vector<Eigen::Vector3d>& positions_mm,
                                          const std::vector<char>& marked, std::vector<Eigen::Vector3d>& displacement_mm,
                                          double smoothing_mm, double max_search_mm);

// Triangles whose normal turned by more than 90 degrees from the start
// surface (or collapsed) when its vertices are at `positions_mm`: folds.
std::vector<int> flipped_triangles(const TriSurface& start, const std::vector<Eigen::Vector3d>& positions_mm);

// Moves the surface from start + from_mm toward start + to_mm only as far as
// the guard allows, per vertex: the vertices of every triangle that would
// break the guard take half their step, again, and after four halvings none
// of it (a bounded number of passes). When start + from_mm keeps the guard,
// so does the result: a step can be shortened, never make a fold. Returns
// the number of vertices held back (to_mm is overwritten).
std::size_t limit_folding(const TriSurface& start, const std::vector<Eigen::Vector3d>& from_mm,
                          std::vector<Eigen::Vector3d>& to_mm, const FoldGuard& guard);

// The same, with the start normals and vertex-triangle lists kept for many
// steps on one surface (the active-surface flow). Keeps a reference to start.
class FoldLimiter {
 public:
  FoldLimiter(const TriSurface& start, const FoldGuard& guard);
  std::size_t limit(const std::vector<Eigen::Vector3d>& from_mm, std::vector<Eigen::Vector3d>& to_mm) const;

 private:
  bool keeps_guard(int triangle, const std::vector<Eigen::Vector3d>& positions_mm) const;
  const TriSurface& start_;
  FoldGuard guard_;
  double cos_max_;
  std::vector<Eigen::Vector3d> n0_;
  std::vector<std::vector<int>> triangles_of_;
};

// Lumped vertex areas (a third of each incident triangle), for area fractions.
std::vector<double> vertex_areas_mm2(const TriSurface& surface);

}  // namespace brainshift
