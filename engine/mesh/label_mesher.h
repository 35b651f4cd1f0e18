#pragma once
// Labeled tetrahedral meshing of a label image (CGAL Mesh_3 behind the scenes).
//
// All non-zero labels that are not cavities form ONE tissue subdomain: thin
// structures (corticospinal tract) must not force interfaces into the mesh;
// they are recovered per tet afterwards (tet_labels) for the materials. The
// exception is interface_labels (a tumor that may be resected): each is its
// own subdomain so that its wall is made of mesh faces.
// Each cavity label (lateral ventricles) is meshed as its own subdomain so its
// wall is resolved, then its tets are dropped: the cavity becomes a hole whose
// wall is a boundary surface (neighbour_label = the cavity label).
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "core/image.h"
#include "core/tet_mesh.h"

namespace brainshift {

struct MeshingParameters {
  // Surface criteria (CGAL Mesh_3 facet criteria), sizes in mm.
  double facet_angle_deg = 25;
  // Defaults tuned on the Colin27 brain (ch2bet > 0, 1.74 L) to give at least
  // the published mesh size (43,584 nodes / 214,035 tets); see README.md.
  double facet_size_mm = 2.0;
  double facet_distance_mm = 1.5;
  // Volume criteria.
  double cell_size_mm = 3.4;
  double cell_radius_edge_ratio = 3;
  // Sliver removal, run WITHOUT time limits so that the result depends only on
  // the input (CGAL's default limit is the refinement time, which made meshes
  // differ between runs). Exudation is bounded by a count of steps instead
  // (exude_steps_per_vertex; see README.md). optimise = false skips both steps.
  bool optimise = true;
  // Perturbation is off by default: on the Colin27 brain it cost 20-50 s of
  // CPU without raising the minimum dihedral angle (that minimum sits on the
  // surface, where perturbation barely moves vertices). Exudation is cheap.
  bool perturb = false;
  double perturb_sliver_bound_deg = 10;  // stop once every dihedral exceeds this
  double exude_sliver_bound_deg = 15;    // 0 = exude as far as possible (slower)
  // Exudation budget: at most this many queue steps (one sliver taken from
  // CGAL's queue: a vertex of it pumped, or the sliver given up) per vertex of
  // the refined mesh. 1 = the work of one pass of the original algorithm
  // (Cheng et al. 2000, every vertex given its weight once); CGAL's queue
  // variant may revisit vertices without end on some maps.
  double exude_steps_per_vertex = 1.0;
  // Refinement stops with ComputeError at this many vertices; 0 = the cap
  // derived from the sizes and the labelled volume and area (README.md).
  std::size_t max_vertices = 0;
  // Drop tissue pieces not connected (through tet faces) to the largest one:
  // islands of mask noise would be free-floating bodies the FEM cannot hold.
  bool keep_largest_component = true;
  // Seeds CGAL's domain random generator (initial points, ray shooting).
  unsigned random_seed = 0;
  std::vector<std::uint16_t> cavity_labels{2};
  // Tissue labels meshed as their own subdomain and kept: mesh faces then
  // follow their interface with the surrounding tissue. For structures that
  // may be resected (the tumor): their wall becomes a surface of mesh nodes
  // that can be matched to a resection cavity. Their tets carry the label.
  std::vector<std::uint16_t> interface_labels;
  // Tet label used where the voxel nearest a tet centroid is 0 or a cavity.
  std::uint16_t default_tissue_label = 1;
};

// Optional diagnostics of one meshing run.
struct MeshingStats {
  double seconds_refine = 0, seconds_optimise = 0, seconds_total = 0;
  std::size_t seed_components = 0;   // labeled components seeded on
  std::size_t dropped_degenerate = 0;
  std::size_t dropped_island_tets = 0;  // tets outside the largest component
  // Refinement: vertices made, and the cap it may not reach (vertex_cap).
  std::size_t refined_vertices = 0, vertex_cap = 0;
  // Exudation: queue steps done, the budget, whether the budget stopped it
  // (slivers were left), slivers (below the bound) before and after, and the
  // smallest dihedral angle of the meshed cells before and after.
  std::size_t exude_steps = 0, exude_budget = 0;
  bool exude_budget_hit = false;
  std::size_t slivers_before = 0, slivers_after = 0;
  double min_dihedral_before_deg = 0, min_dihedral_after_deg = 0;
};

// The stage a meshing run has reached, for progress reports: "refine" when the
// refinement is done, "exude" when exudation is done (stats so far filled).
using MeshingProgressFn = std::function<void(const std::string& stage, const MeshingStats& so_far)>;

// Meshes `labels` (0 = outside). Node coordinates are world RAS+ mm
// (labels.grid.world_from_voxel, which may be oblique or flipped); every tet is
// positively oriented; boundary faces point out of the tissue; nodes follow a
// Morton curve (contiguous node ranges are spatially compact, which the FEM's
// contiguous MPI partition relies on) and tets are sorted by smallest node.
// Deterministic: same input and parameters give the identical mesh.
// Bounded: refinement stops at MeshingStats::vertex_cap vertices (then
// ComputeError naming the cap), exudation after exude_budget steps (the mesh is
// kept; the stats say so).
// Throws InputError for an empty/invalid image or parameters, ComputeError when
// CGAL yields no tissue tets or the refinement reaches its vertex cap.
TetMesh mesh_label_image(const LabelImage& labels, const MeshingParameters& params,
                         MeshingStats* stats = nullptr, const MeshingProgressFn& progress = nullptr);

}  // namespace brainshift
