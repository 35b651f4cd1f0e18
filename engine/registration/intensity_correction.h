#pragma once
// The intensity refinement's dense correction: the lattice's v composed with
// the FEM's pull-back over the brain region (registration/intensity_refinement.h).
// Internal to the refinement.
#include <cstddef>

#include "core/image.h"
#include "image/image_stats.h"
#include "registration/intensity_lattice.h"

namespace brainshift::intensity {

struct CorrectionStats {
  double max_mm = 0, sum_mm = 0;  // |u' - u| inside the brain region
  std::size_t voxels = 0;
};

// u becomes u'(x) = w(x) + u(x + w(x)) over box, w = fade(x) v(x): fade is 1
// inside the brain region (sdf_mm <= 0) and falls smoothly to 0 at fade_mm
// outside it.
CorrectionStats apply_correction(VectorImage3& u, const Lattice& l, const ImageF& sdf_mm, const VoxelBox& box,
                                 double fade_mm);

}  // namespace brainshift::intensity
