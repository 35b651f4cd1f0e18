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
#include "pipeline/given_labels_use.h"
#include "registration/active_surface.h"
#include "registration/affine_registration.h"
#include "registration/intensity_refinement.h"
#include "registration/surface_repair.h"
#include "segmentation/intraop_segmentation.h"
#include "segmentation/label_image_check.h"

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

// The image-only path's passes of the stages (docs/DESIGN.md "Automatic
// intraop segmentation", item 9). A pass a re-match follows only carries the
// preop labels for the re-match's prior, which is 1 mm wide and which the
// image overrules where tissue moved: shortcuts that change that prior by
// much less than its width; the gates (folds, motion beyond the data) still
// decide whether the pass is non-rigid, and a light pass they refuse is run
// again in full.
struct PassShortcuts {
  // The prior-only pass: the T1 refinement of the interior (about 0.5 mm,
  // capped at 3). On by default: without it (and with 10 membrane iterations
  // per level) the re-match's brain Dice fell by 0.003-0.005 and the TRE rose
  // by 0.03-0.05 mm on the robustness cases measured (docs/PERFORMANCE.md
  // 12.7): the prior is worth its refinement.
  bool prior_refine = true;
  // The prior-only pass: membrane iterations per stiffness level of the
  // outer and ventricle matches (0 = as the answer's; see prior_refine).
  int prior_surface_max_iterations = 0;
  // A re-match's pass: the affine starts from the previous pass's, whose
  // segmentation differs by about a voxel at the outline (finest level only).
  bool warm_start_affine = true;
  // The first round (the head's placement, the first segmentation, its light
  // pass) only makes the re-match's prior, 1 mm wide: with a spacing > 0
  // it is worked on a grid coarsened to it (as pipeline/working_grid.h
  // coarsens), the re-match and the answer on the scan's working grid; a
  // first round refused there is decided again on the scan's own grid
  // (docs/DESIGN.md "Automatic intraop segmentation", item 9). 2 mm (the
  // mesh's surface facet): with the answer's stages on the stage grid a
  // 0.94 mm scan's image-only time falls by about 0.75 s (4.07 -> 3.30 s
  // in-process, paired), and over the robustness suite, the hospital suite
  // and two held-out families (51 cases) the mean TRE moved by
  // -0.007..+0.006 mm per suite (docs/PERFORMANCE.md 12.30). Alone (12.26)
  // it had cost 0.003-0.008 mm. The re-match's volume-gate margin on the
  // 20-22 mm sinkings is 1.5-2.6 points either way. 0: off.
  double prior_spacing_mm = 2.0;
  // A full pass (the answer's) works its stages (affine, surfaces, solve,
  // field, refinement, gates) on a grid coarsened to this spacing (as
  // pipeline/working_grid.h coarsens), the segmentation staying on the
  // scan's working grid: each stage voxel takes the segmentation's label
  // covering most of it, the image smoothed to the coarser voxels, the
  // field carried back trilinearly and the preop warped again on the
  // scan's grid (its Jacobian there reported as jacobian.delivered_min). 2 mm, the
  // mesh's surface facet ([mesh] facet_size_mm): what the stages make is the
  // mesh's nodal displacement, linear within each tetrahedron (cells
  // 3.4 mm), which a grid at the facet size samples at its own scale. The
  // light pass stays on the scan's grid (ScanOnGrid::stages,
  // segmentation_rounds.h, says why).
  // Measured (docs/PERFORMANCE.md 12.29): 0.17-0.4 s less a scan, mean TRE
  // lower on the robustness suite and three hospital families, the
  // segmentation unchanged. 0: off.
  double stage_spacing_mm = 2.0;
};

// The automatic path: a scan given as an image alone (pipeline/prepare_stage.h;
// docs/DESIGN.md "Automatic intraop segmentation" says why each value).
struct AutoSegmentationParameters {
  segmentation::SegmentationParameters classifier;
  // Prior width (mm) after the head's alignment alone: the rigid positioning
  // is known to a voxel or two, the brain's own shift is not (5-25 mm at the
  // cortex, 1-3 mm deep); the image overrules the prior where tissue has moved
  // (prior_floor), the width only has to cover the deep shift and the head
  // alignment's error.
  double prior_width_affine_mm = 3.0;
  // Inside the carried outline after the head's alignment alone: the cortex
  // under a craniotomy sinks by up to about 25 mm, where fluid or air takes
  // its place; a logistic over 5 mm leaves the outside 1 % (-4.6 nats) at
  // that depth, so that fluid there is decided by the image.
  double prior_inward_width_affine_mm = 5.0;
  // Outside the outline a non-rigid estimate carries: its error, about 1 mm
  // at the landmarks. Not a voxel more for partial volume: that is the
  // image's to decide (its likelihood). Where the image cannot tell (a T2's
  // fluid-bone mixture beyond the cortex looks like tissue), the
  // classification follows the prior's tail, and 1.5 mm let it take brain
  // 2-4 mm beyond the carried outline (docs/DESIGN.md "Automatic intraop
  // segmentation", item 2; docs/PERFORMANCE.md 12.38).
  double prior_width_nonrigid_mm = 1.0;
  // Inside it: the same error. Wider (1.5 or 2 mm, so that a layer the
  // first round took beyond the cortex is given back more easily) was
  // measured: brain Dice lower, FLAIR-like images less accurate, and a pure
  // translation of the test head recovered 0.57 mm off at 1.5 (0.46 at 1).
  double prior_inward_width_nonrigid_mm = 1.0;
  // The ventricles after the head's alignment alone (tissue_prior.h): they
  // may have moved by up to ventricle_shift_affine_mm (deep structures shift
  // by several mm, up to about 10 under a large craniotomy, farther than the
  // ventricles' bodies are thick), the image decides within that distance of
  // the carried ventricles, the prior falls off beyond it over
  // ventricle_prior_width_mm. After the non-rigid estimate no shift margin,
  // the width its error at the ventricles (about a voxel).
  double ventricle_shift_affine_mm = 6.0;
  double ventricle_prior_width_mm = 1.5;
  // A bright-fluid (T2-like) image's first round (after the head's
  // alignment alone) is fitted again with the bias at this degree when it is
  // below the classifier's (bias_degree, 2); the re-match rounds keep the
  // classifier's. The wide prior leaves more of the brain's core uncertain
  // (a resection's margin, oedema, the rim inside the prior), and a
  // quadratic fitted on it can bend to that anatomy: on held-out family 6's
  // T2-like resection it spanned 0.41-1.23 across the brain (the scanner's
  // 0.8-1.2), raised grey matter past half fluid and the rim peel took 87 ml
  // of cortex. At 1 the 14 T2-like scans of seven families registered
  // better (mean TRE 0.488 -> 0.467 mm, lowest brain Dice 0.964 -> 0.968),
  // but every first round then kept ~8 % more brain (the rim a linear field
  // leaves unpeeled), 1.2-2.6 points from the volume gate's +10 %: an
  // atrophied brain's wider rim would be refused. Off (2) by default
  // (docs/DESIGN.md "Automatic intraop segmentation", item 12).
  int bright_fluid_bias_degree_affine = 2;
  // The grid a scan is worked on (pipeline/working_grid.h): an axis of the
  // image or given labels finer than this by more than a quarter is
  // coarsened to it for the segmentation and the stages, and the answer is
  // carried back to the scan's own grid. Half the mesh's surface facet
  // (about 2 mm): the finest detail the mesh can take from a segmentation;
  // and the finest spacing the suites validated the segmentation at
  // (0.94-1 mm). 0: off.
  double working_spacing_mm = 1.0;
  // Segment -> register rounds after the first (bounded; 0 = one pass).
  int rematch_rounds = 1;
  PassShortcuts passes;
  // true: a re-match reuses the round before's fitted classes and bias (the
  // same image: scanner, coil, tissues) and only the prior is new, no EM fit
  // (about 0.3 s of CPU). Off: measured less accurate (docs/PERFORMANCE.md
  // 12.8: brain Dice lower on 5 of the 6 robustness cases run, TRE p95 2.1
  // and 2.0 mm instead of 0.85 and 1.02 on two): the first round's classes
  // were fitted under the wide prior of the head placement, over fluid and
  // dura that the re-match's narrow prior no longer gives to the brain.
  bool rematch_reuses_fit = false;
  // true: a re-match moves out only open fluid touching the gap the round
  // before found (segmentation/intraop_segmentation.h segment_intraop): the
  // re-match's narrower prior exposed the basal cisterns under swellings as
  // "gaps" (docs/DESIGN.md "Automatic intraop segmentation", item 7).
  bool rematch_gaps_found_before = true;
  // Gates. Brain volume (the outline, after the affine's volume change is
  // divided out) against the preop's: brain shift changes it by a few per
  // cent (fluid drained, oedema), a resection by the resectable structures'
  // volume; a leak into fluid or dura, or a lost lobe, by tens of per cent.
  double max_brain_volume_change = 0.10;
  // Ventricles found, as a fraction of the preop ventricles: compression by
  // mass effect or drainage shrinks them, but below this their wall would be
  // matched to noise.
  double min_ventricle_fraction = 0.2;
  // The outer surface is trusted where the posterior of the chosen tissue one
  // voxel inside it is at least this (a coin toss between tissues is 0.5);
  // below it over more than max_uncertain_surface_fraction of the surface,
  // the match would follow guesses (about the area of a large craniotomy).
  double min_surface_confidence = 0.6;
  double max_uncertain_surface_fraction = 0.2;
  // A scan given with labels and an image: the labels checked against the
  // image (segmentation/label_image_check.h); gross disagreement gives the
  // marked affine-only result for labels used exactly, and the image's own
  // answer with a caution for labels to be refined.
  bool check_given_labels = true;
  // Labels pushed with their image: how the stages use them (a push may say,
  // protocol labels_use). refine: the labels' pass carries the preop onto the
  // image, the image is classified under it as a re-match is, and that
  // segmentation is registered; labels an algorithm made (a threshold, a
  // network) err by millimetres where the image does not: on the hospital
  // suite and three held-out families mean TRE 0.53-0.56 -> 0.38-0.39 mm,
  // worst landmark 10-11 -> 5-6 mm, for about 1.5 s more (docs/DESIGN.md
  // "Labels with their image", docs/PERFORMANCE.md 12.31). exact: the labels
  // as given (a segmentation corrected by hand; the one-pass path). A
  // refinement the classifier, its gates or the stages refuse leaves the
  // labels' pass standing.
  GivenLabelsUse given_labels = GivenLabelsUse::refine;
  segmentation::LabelImageCheckParameters label_image_check;
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
  AutoSegmentationParameters auto_segmentation;  // scans given as an image alone
  // Is the input and the answer physically possible (DESIGN.md, "Plausibility gates").
  PlausibilityLimits plausibility;
  // The map computed after the answer is served (DESIGN.md, "Uncertainty map").
  UncertaintyParameters uncertainty;
  // Bounds on images received from outside (bytes after decompression).
  std::size_t max_image_bytes = std::size_t{512} << 20;
};

}  // namespace brainshift
