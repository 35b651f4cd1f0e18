#pragma once
// Every tunable of the pipeline as plain data. The engine never parses
// configuration: config/ (TOML) and the protocol fill this struct.
#include <cstddef>
#include <string>

#include "field/displacement_field.h"
#include "field/unfold.h"
#include "fem/elastic_model.h"
#include "mesh/label_mesher.h"
#include "models/surface_models.h"
#include "quality/plausibility_gates.h"
#include "quality/uncertainty_map.h"
#include "core/label_table.h"
#include "registration/active_surface.h"
#include "registration/affine_registration.h"
#include "registration/intensity_refinement.h"
#include "registration/surface_repair.h"

namespace brainshift {

struct QualityGates {
  // A field whose Jacobian determinant falls to or below this inside the brain
  // is folded: the non-rigid result is refused and the affine-only fallback is
  // returned, clearly marked. 0 = refuse exactly the folded fields (strong but
  // valid compression under an 18 mm sinking reaches det ~0.01-0.05).
  double min_jacobian_determinant = 0.0;
  // Surface-match residual (mm, mean over vertices) above which the match is
  // declared diverged.
  double max_mean_surface_residual_mm = 3.0;
  // A matched surface (and the field's largest displacement) may exceed the
  // farthest the data ask a vertex to travel (|signed distance| at the start
  // positions) by at most this (mm): normal-only forces move a vertex along
  // its normal to the target, the membrane adds tangential relaxation (<= 2 mm
  // measured at the flanks of a dent) and the T1 refinement up to its 3 mm
  // cap. Anything beyond was not asked for by the data (docs/DESIGN.md).
  double max_unsupported_displacement_mm = 5.0;
  // Intraop brain volume below this fraction of the preop brain volume means the
  // field of view misses most of the brain.
  double min_intraop_brain_fraction = 0.5;
};

struct PipelineParameters {
  LabelTable label_table;  // from config/labels.toml (config::default_label_table()) or the user's
  MeshingParameters meshing;
  ElasticOptions elastic;
  AffineRegistrationParameters affine;
  ActiveSurfaceParameters outer_surface;      // outer brain surface
  ActiveSurfaceParameters ventricle_surface;  // lateral-ventricle wall
  ActiveSurfaceParameters resection_surface;  // wall of a resected structure -> cavity
  SurfaceRepairParameters surface_repair;     // local repair of outer and ventricle matches
  // An intraop cavity of at least this volume (ml) next to a resectable
  // structure means it was resected (smaller holes are segmentation noise).
  double min_resection_cavity_ml = 0.1;
  FieldParameters field;
  // Interior correction from the intraop T1 after the solve (skipped without one).
  IntensityRefinementParameters intensity;
  UnfoldParameters unfold;  // local repair tried before the fold gate refuses a field
  ModelParameters models;
  QualityGates gates;
  // Is the input and the answer physically possible (DESIGN.md, "Plausibility gates").
  PlausibilityLimits plausibility;
  // The map computed after the answer is served (DESIGN.md, "Uncertainty map").
  UncertaintyParameters uncertainty;
  // Bounds on images received from outside (bytes after decompression).
  std::size_t max_image_bytes = std::size_t{512} << 20;
};

}  // namespace brainshift
