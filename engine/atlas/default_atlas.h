#pragma once
// The default preoperative atlas: Colin27 ("ch2", 1 mm, 181x217x181) T1 and a
// label map on the same grid:
//   1 brain parenchyma, 2 lateral ventricles, 3 corticospinal tract (CST).
//
// Method (all resampling goes through world coordinates, never voxel to voxel):
// - Brain: ch2bet > 0 on ch2's grid (resampled if its geometry differs), then
//   the largest 6-connected component, holes filled, closed with a 2 mm ball
//   (bridges one-voxel notches) and opened with a 1 mm ball (drops strands one
//   voxel thin), then largest component and hole filling again.
// - Lateral ventricles: ch2better (0.5 mm, brain only, CSF set to 0) is resampled
//   linearly onto ch2's grid. CSF candidates are voxels of the brain eroded by
//   3 mm (cuts off cortical sulci) where the resampled ch2better is < 30 (CSF
//   with partial volume) and the ch2 T1 is < 60 (ch2 CSF ~30, grey matter ~80,
//   white matter ~110). 6-connected components of at least 0.5 ml are kept when
//   their centroid lies in the central box |x| < 30, -45 < y < 35, 0 < z < 40 mm
//   (the bodies of the lateral ventricles, above the thalamus). The 3rd and 4th
//   ventricles and the temporal horns are not kept (their centroids lie below or
//   outside the box; on Colin27 they are separate components). The result is closed by 1 mm and
//   restricted to the brain. On Colin27 this gives one component (the two
//   ventricles touch through the thin septum) of ~20 ml.
// - CST: JHU-WhiteMatter-labels-1mm labels 7,8 (brainstem CST), 15,16 (cerebral
//   peduncle), 19,20 (posterior limb of the internal capsule), 25,26 (superior
//   corona radiata), nearest-neighbour resampled onto ch2's grid, restricted to
//   the brain. Ventricles take precedence over CST where they overlap.
#include <filesystem>

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "core/image.h"
#include "core/label_table.h"
#include "image/morphology.h"

namespace brainshift {

// The atlas's own label values. The shipped label table (config/labels.toml)
// uses the same numbers; a site's table with other values gets the atlas
// through atlas_labels_for (by structure name).
namespace atlas_labels {
inline constexpr std::uint16_t background = 0;
inline constexpr std::uint16_t brain = 1;
inline constexpr std::uint16_t ventricles = 2;
inline constexpr std::uint16_t corticospinal_tract = 3;
}  // namespace atlas_labels

struct DefaultAtlas {
  ImageF t1;           // ch2 T1 on its native grid
  LabelImage labels;   // same grid: 0 background, 1 brain, 2 ventricles, 3 CST
};

// The pieces, for other label maps of the same head (phantom/independent_labels.h):
// the JHU corticospinal-tract labels on `grid`, and the label map of a brain
// mask with its ventricles and tract (ventricles win over the tract).
Mask jhu_corticospinal_tract(const std::filesystem::path& templates_dir, const Grid3& grid);
LabelImage compose_atlas_labels(const Mask& brain, const Mask& ventricles, const Mask& cst);

// The atlas's labels in the values of `table`, matched by structure name
// (brain, ventricles, corticospinal_tract). A structure the table lacks
// becomes the table's parenchyma: it is tissue the site does not track.
LabelImage atlas_labels_for(const LabelImage& atlas, const LabelTable& table);

DefaultAtlas build_default_atlas(
    const std::filesystem::path& templates_dir = "/usr/share/mricron/templates");

// Builds once and caches t1.nii.gz, labels.nii.gz and provenance.json in
// cache_dir; later calls reload them. The cache is rebuilt when a file is
// missing, unreadable, the provenance version differs, or the two images do not
// share a grid. Files are written under temporary names and renamed, the
// provenance last, so an interrupted build is detected as a missing cache.
DefaultAtlas load_or_build_default_atlas(
    const std::filesystem::path& cache_dir,
    const std::filesystem::path& templates_dir = "/usr/share/mricron/templates");

}  // namespace brainshift
