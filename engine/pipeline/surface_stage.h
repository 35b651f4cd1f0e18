#pragma once
// The per-scan surface stage: every mesh boundary surface (outer brain,
// ventricle walls) matched to its intraop structure, defects repaired locally,
// and the non-rigid displacement of every fixed FEM node returned.
//
// Graded gates (DESIGN.md, "Surface quality gates"): a local defect of a match
// is repaired, and reported in metrics.surfaces.<name>.repair, never silently:
//   - defects: vertices of flipped triangles, of crossing triangle pairs, and
//     vertices left farther than unreliable_residual_mm from their target;
//   - repair: those vertices, grown by one ring per round, take their
//     displacement from their reliable neighbours (registration/surface_repair.h);
//     the repaired surface is checked again, up to `rounds` times.
// Folds the fill makes are taken back by the fold guard (surface_repair.h)
// toward the match, which the guard kept unfolded. How much was repaired is
// reported, not judged: a large repaired area on a good match is a noisy
// segmentation, not an unsafe field. The scan falls back to affine-only
// (failure set) only when the result would be unsafe: the match diverged
// (mean residual over the gate), the surface still folds or crosses itself,
// or it moves farther than the data can justify (the largest distance of a
// start vertex from its target, plus max_unsupported_mm).
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "pipeline/engine_session.h"
#include "pipeline/warm_state.h"
#include "registration/active_surface.h"
#include "registration/boundary_samples.h"
#include "registration/surface_repair.h"

namespace brainshift {

struct RepairedMatch {
  SurfaceMatchResult match;  // displacement_mm repaired; residuals and iterations of the match itself
  nlohmann::json repair;     // what was found and done (metrics.surfaces.<name>.repair)
  std::string unsafe;        // why the match must not drive the FEM; empty when it may
};

// One surface (intraop frame, after the affine): matched with its facing-wall
// contacts kept apart, then repaired as described above.
RepairedMatch match_and_repair(const TriSurface& start, const ContactPairs& contacts, const ImageF& target_sdf_mm,
                               const ActiveSurfaceParameters& params, const SurfaceRepairParameters& repair,
                               const ImageF* intraop_image, double max_unsupported_mm);

// The elastic field's largest nodal displacement against the largest
// prescribed one (the matched surfaces): an interior that moves farther than
// its boundary by more than gates.max_unsupported_displacement_mm was not
// asked for by the data. Adds both to `report`; returns the reason or "".
std::string field_beyond_data(const std::vector<Eigen::Vector3d>& nodal_mm, const std::vector<Eigen::Vector3d>& fixed_mm,
                              const QualityGates& gates, nlohmann::json& report);

std::vector<Eigen::Vector3d> match_surfaces(const WarmState& warm, const IntraopDistanceMaps& maps,
                                            const Eigen::Matrix4d& intraop_from_preop, const IntraopInput& input,
                                            const PipelineParameters& params, nlohmann::json& metrics,
                                            std::string* failure);

}  // namespace brainshift
