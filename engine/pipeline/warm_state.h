#pragma once
// Everything the intraop stages reuse from the preop phase, kept in memory on
// rank 0 between scans (the FEM part also lives on the workers).
#include <array>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/surface_contact.h"
#include "core/tet_mesh.h"
#include "image/image_stats.h"
#include "models/carry.h"
#include "pipeline/engine_session.h"
#include "pipeline/fem_cluster.h"
#include "quality/left_right_check.h"
#include "registration/boundary_samples.h"
#include "registration/intensity_placement.h"

namespace brainshift {

// A boundary surface of the mesh and the intraop structure it is matched to.
struct MatchedSurface {
  std::string name;                      // "outer" or the cavity label's name
  std::uint16_t cavity_label = 0;        // 0 for the outer surface
  TriSurface surface;                    // preop, vertices tied to mesh nodes
  ContactPairs contacts;                 // its facing walls (mesh/surface_contacts.h), preop frame
};

// A structure that may be resected (the tumor): its wall, and the FEM system
// in which that wall is fixed as well as the brain surface and cavity walls.
struct ResectableWall {
  std::string name;
  std::uint16_t label = 0;
  TriSurface wall;                        // preop, normals out of the structure
  int system = 0;                         // FemCluster system index
  std::vector<int> fixed_index_of_node;   // node -> index into fixed_nodes(system), or -1
  double volume_ml = 0;                   // preop volume of the structure
};

struct PreopModel {
  TriSurface surface;     // preop frame
  ModelBinding binding;   // where each vertex sits in the mesh
};

// What the input's plausibility gates need of the preop alone, the same for
// every scan (pipeline/plausibility_stage.h): made with the models.
struct PlausibilityPreop {
  LeftRightPreop left_right;       // the table's asymmetric structures
  double ventricle_volume_ml = 0;  // the table's first cavity label
};

struct WarmState {
  explicit WarmState(MPI_Comm comm) : fem(comm) {}

  PreopInput preop;
  FemCluster fem;                          // owns the mesh every rank shares
  std::vector<MatchedSurface> surfaces;    // outer first, then cavity walls
  std::vector<int> fixed_index_of_node;    // node -> index into fixed_nodes(0), or -1
  std::vector<ResectableWall> resectables; // each with its own system (1, 2, ...)
  PreopBoundarySamples affine_samples;     // boundary points for the affine stage
  std::map<std::string, PreopModel> models;
  double brain_volume_ml = 0;
  std::optional<PlausibilityPreop> plausibility_preop;
  nlohmann::json timings;                  // preop stage seconds
  // The preop head (coarse grid), for placing the preop on a scan given
  // without labels (prepare_stage.h); made on the first such scan.
  std::optional<Mask> preop_head;
  // The preop T1's brain samples for placing it by intensity
  // (registration/intensity_placement.h), made on the first scan that needs
  // them: a brain-extracted preop, or scan.
  std::optional<IntensityPlacementPreop> intensity_placement_preop;
  // The head's pose on the last scan whose placement the pose search checked
  // (segmentation_rounds.h place_preop_by_head): the head stays pinned in its
  // clamp through the operation, so a later scan placed within a few degrees
  // of it needs no new search.
  std::optional<Eigen::Matrix4d> checked_head_pose;
  // The preop labels' tissue box (field/tissue_guard.h), worked out by the
  // first scan's field.
  std::optional<VoxelBox> preop_tissue_voxels;
  // The preop T1's median in its ventricles and in its parenchyma (fluid,
  // tissue), for telling fluid the preop already held from a gap
  // (segmentation::PreopSeen); made on the first scan given without labels.
  std::optional<std::array<double, 2>> preop_fluid_tissue_medians;
  // The preop T1 at the resolution of the grids the interior refinement
  // last worked on (preop_t1_at_resolution): a scanner sends every scan of
  // a session on the same grid, and the image-only path's two passes share
  // one, so the blur (about 0.15 s) is made once, not per pass.
  struct BlurredPreop {
    Eigen::Vector3d sigma_voxels;
    ImageF t1;
  };
  std::vector<BlurredPreop> preop_t1_blurred;
};

// The preop T1 as a scanner with `grid`'s voxels records it
// (registration/intensity_refinement.h, match_point_spread), kept in
// warm.preop_t1_blurred for the last two resolutions asked for.
const ImageF& preop_t1_at_resolution(WarmState& warm, const Grid3& grid);

// The preop phase on rank 0 (drives the workers through fem).
std::unique_ptr<WarmState> build_warm_state(MPI_Comm comm, PreopInput input,
                                            const PipelineParameters& params,
                                            const ProgressFn& progress,
                                            std::optional<TetMesh> stored_mesh);

// A transform the affine-only fallback delivers, and what it is (reported
// in metrics.affine.fallback_transform).
struct FallbackTransform {
  Eigen::Matrix4d intraop_from_preop = Eigen::Matrix4d::Identity();
  std::string what;
};

// What a pass of the stages is for, and where it may start. The answer needs
// everything; the image-only path's pass a re-match follows only carries the
// preop labels for the re-match's prior (prepare_stage.h): its field, its
// gates and its warped labels, no warped T1, no models, and the shortcuts of
// AutoSegmentationParameters::passes (docs/DESIGN.md "Automatic intraop
// segmentation", item 9). Such a result is never the answer: the caller runs
// the full pass when it would be.

struct PassOptions {
  bool prior_only = false;
  // The affine's warm start (register_affine): a previous pass's, on a
  // nearly identical segmentation; nullptr: the full search.
  const Eigen::Matrix4d* affine_start = nullptr;
  // Without a warm start, one more start for the affine's search
  // (register_affine's candidate): the image-only path's head placement.
  const Eigen::Matrix4d* affine_candidate = nullptr;
  // The field keeps preop tissue out of the gap a sinking left
  // (field/tissue_guard.h), judged against the pass's own outline. Off for
  // the pass on given labels that their image refines: that pass makes the
  // refinement's prior, which must carry the preop where a segmenter missed
  // brain (its outline is what the refinement corrects).
  bool guard_tissue = true;
  // The pass's labels are the engine's own segmentation (made under the
  // preop prior): the guard judges every voxel beyond their outline. Given
  // labels keep a tolerance of their outline's uncertainty (TissueGuard::
  // outline_tolerance_mm), within which a segmenter may have eroded brain.
  bool segmented_by_engine = false;
  // What a forced fallback delivers instead of the pass's affine: set when
  // labels that came with their image were refused (by the labels-vs-image
  // check, or by the gates that judge their geometry), since the affine
  // fitted to them carries their error, a shift included
  // (pipeline/labels_with_image.cpp). Unset: the affine, or its rigid part
  // after the gates refused the labels' geometry.
  std::optional<FallbackTransform> forced_fallback_transform = std::nullopt;
  // The forced fallback's reason judged the geometry of the labels the affine
  // is fitted to (SegmentationGates::geometry_refused): the affine's rigid
  // part is delivered, as after the stages' own gates refused it.
  bool forced_fallback_rigid = false;
};

// The intraop stages on rank 0. Without quality metrics, result.metrics holds
// only what the registration itself reports (affine, surfaces, solve,
// Jacobian, result kind); add_quality_metrics() completes it later.
// forced_fallback: a reason found before the stages (a gate of the automatic
// segmentation) to return the affine-only result; empty for the normal path.
ScanResult run_intraop(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                       const ProgressFn& progress, bool with_quality_metrics = true,
                       const std::string& forced_fallback = "", const PassOptions& pass = {});
void add_quality_metrics(const WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                         ScanResult& result, const ProgressFn& progress);
// A prior-only pass (PassOptions) made the answer: adds what it skipped, the
// warped T1 and the models, from its own field and nodal displacements. Only
// for a pass whose field is a full pass's (no field-changing shortcut of
// AutoSegmentationParameters::passes); otherwise run the full pass.
void complete_prior_pass(const WarmState& warm, ScanResult& result, const ProgressFn& progress);

// Checks shared by both phases (InputError with a clear message).
void validate_preop_input(const PreopInput& input, const LabelTable& table);
void validate_intraop_input(const IntraopInput& input, const LabelTable& table);

}  // namespace brainshift
