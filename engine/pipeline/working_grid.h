#pragma once
// The grid an image-only scan is worked on. The automatic segmentation and
// the stages cost time and memory in proportion to the voxels (a 0.7 mm
// isotropic 3 T scan holds 18 million, 4.7x the suites' 1.5 T scans, and took
// a minute and 3.6 GB). Detail finer than half the mesh's surface facet
// cannot reach the elastic model, so an axis much finer than
// AutoSegmentationParameters::working_spacing_mm is coarsened to it for the
// work, and the answer is carried back to the image's own grid, the grid
// every output is defined on (docs/DESIGN.md "The working grid").
#include <string>

#include "image/resample.h"
#include "pipeline/warm_state.h"

namespace brainshift {

// working_grid and kWorkingGridMinCoarsening: image/resample.h (the label
// check coarsens by the same rule).

// A result worked out on a coarser grid of the same extent, carried to the
// image's grid (given labels' grid too): the field sampled trilinearly (it is smooth on the scale of
// the working voxels: the elastic solution between mesh nodes 2-3 mm apart),
// the preop T1 and labels warped again through it, the segmentation by the
// nearest working voxel, its confidence linearly. Models, the affine and the
// per-node displacements do not depend on a grid.
void carry_to_grid(const WarmState& warm, ScanResult& result, const Grid3& image_grid);

// What a scan worked on a working grid reports: metrics `key` (the working
// grid's and the image's dims and spacing) and timings.intraop `key` (the
// seconds spent coarsening and carrying back), added to the total. The
// image-only passes' stage grid (PassShortcuts::stage_spacing_mm) reports
// the same way under "stage_grid".
void report_working_grid(ScanResult& result, const Grid3& work, const Grid3& image_grid, double seconds,
                         const std::string& key = "working_grid");

// The stages on given labels (and their image): on the working grid when the
// labels' grid has an axis much finer than working_spacing_mm (each working
// voxel takes the label covering most of it, downsample_labels; the image
// smoothed and sampled as for the automatic path), the answer carried back
// to the labels' grid; run_intraop as it is otherwise. Without quality metrics: the caller adds them against the
// labels as given.
ScanResult run_intraop_on_working_grid(WarmState& warm, const IntraopInput& input, const PipelineParameters& params,
                                       const ProgressFn& progress, const std::string& forced_fallback = "",
                                       const PassOptions& pass = {});

}  // namespace brainshift
