#pragma once
// Local repair of a folded pull-back field.
//
// Large prescribed surface displacements (an 18-20 mm sinking) can compress a
// few small elements near the cortex to (or past) zero volume. The rest of the
// field is sound, and returning the affine alone for the whole brain would
// throw away a good registration. So before the fold gate refuses a field,
// the voxels whose Jacobian determinant is below a floor are smoothed locally:
// the field is replaced by the average of its 3x3x3 neighbourhood in a small
// box around each bad voxel, which lowers the local gradient and raises the
// determinant toward 1, and this is repeated until no voxel of the region is
// below the floor or the round limit is reached. The change is confined to the
// neighbourhood of the bad voxels and is reported, never silent.
#include <cstddef>

#include "core/image.h"
#include "image/morphology.h"

namespace brainshift {

struct UnfoldParameters {
  double min_determinant = 0.1;  // floor the repaired voxels must reach
  int max_rounds = 30;
  int radius_voxels = 2;         // half-width of the smoothed box around a bad voxel
};

struct UnfoldStats {
  std::size_t bad_voxels_before = 0;  // below the floor inside the region
  std::size_t bad_voxels_after = 0;
  std::size_t changed_voxels = 0;     // voxels whose vector was modified
  int rounds = 0;
  double max_change_mm = 0;           // largest change of one voxel's vector
};

// Repairs field in place inside region (e.g. the intraop brain). Returns true
// when no voxel of region is left below min_determinant.
bool unfold_field(VectorImage3& field, const Mask& region, const UnfoldParameters& params,
                  UnfoldStats* stats = nullptr);

}  // namespace brainshift
