#include "image/label_placement.h"

#include <cmath>

#include "core/errors.h"

namespace brainshift {
namespace {

std::string dims_text(const Grid3& g) {
  return std::to_string(g.dims[0]) + "x" + std::to_string(g.dims[1]) + "x" + std::to_string(g.dims[2]);
}

}  // namespace

LabelImage labels_on_image_grid(LabelImage labels, const Grid3& image_grid, const std::string& what) {
  if (labels.grid.same_geometry(image_grid)) return labels;
  const std::string differs = what + ": grid differs from the image's (" + dims_text(labels.grid) + " against " +
                              dims_text(image_grid) + " voxels, or their world_from_voxel)";
  // The labels' first voxel in the image's voxel coordinates: a whole
  // number along each axis when they are a part of the image's grid.
  const Eigen::Vector3d first = (image_grid.voxel_from_world() * labels.grid.world_from_voxel.col(3)).head<3>();
  constexpr double kFarthestShift = 1e6;  // voxels; keeps the rounding in int range
  if (!first.allFinite() || first.cwiseAbs().maxCoeff() > kFarthestShift) throw InputError(differs);
  const Eigen::Vector3i shift = first.array().round().cast<int>();
  Grid3 part;
  part.dims = labels.grid.dims;
  part.world_from_voxel = image_grid.world_from_voxel;
  part.world_from_voxel.col(3) = image_grid.world_from_voxel * Eigen::Vector4d(shift[0], shift[1], shift[2], 1.0);
  if (!labels.grid.same_geometry(part))
    throw InputError(differs + "; not a part of the image's grid shifted by whole voxels");
  LabelImage placed(image_grid, 0);
  std::size_t beyond = 0;
  for (int k = 0; k < part.dims[2]; ++k)
    for (int j = 0; j < part.dims[1]; ++j)
      for (int i = 0; i < part.dims[0]; ++i) {
        const std::uint16_t value = labels.at(i, j, k);
        if (value == 0) continue;
        const int x = i + shift[0], y = j + shift[1], z = k + shift[2];
        if (x < 0 || y < 0 || z < 0 || x >= image_grid.dims[0] || y >= image_grid.dims[1] || z >= image_grid.dims[2])
          ++beyond;
        else
          placed.at(x, y, z) = value;
      }
  if (beyond > 0)
    throw InputError(what + ": " + std::to_string(beyond) +
                     " labelled voxels lie beyond the image's grid (their box is a part of it shifted by " +
                     std::to_string(shift[0]) + ", " + std::to_string(shift[1]) + ", " + std::to_string(shift[2]) +
                     " voxels); the labels were drawn on another image");
  return placed;
}

}  // namespace brainshift
