#pragma once
// Labels drawn on a part of their image's grid. A segmentation editor may
// store only the box around its segments: 3D Slicer's .seg.nrrd keeps the
// reference volume's spacing and axes but has an extent and origin of its
// own (the NRRD's standard fields give them; Slicer's documentation says to
// read those, not Segmentation_ReferenceImageExtentOffset). Such labels are
// the image's voxels shifted by whole voxels: they are placed on the image's
// grid exactly, no resampling, background beyond their box. Labels on any
// other grid are refused: resampling a segmentation moves its outline by up
// to half a voxel, a choice for the site that drew it, not for us.
#include <string>

#include "core/image.h"

namespace brainshift {

// The labels on image_grid: as they are when on the same grid
// (Grid3::same_geometry); placed when their grid is image_grid's along the
// same axes, shifted by whole voxels (to same_geometry's tolerance), their
// box inside the image's or reaching beyond it with background only.
// InputError, the message starting with `what`, for any other grid ("grid
// differs") and for labelled voxels beyond the image's grid.
LabelImage labels_on_image_grid(LabelImage labels, const Grid3& image_grid, const std::string& what);

}  // namespace brainshift
