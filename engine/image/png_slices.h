#pragma once
// Quick-look PNG slices for humans: a grayscale slice with a coloured label
// overlay. Voxel axes are shown as stored (no reorientation); rows are flipped
// so that the second displayed axis increases upwards.
#include <filesystem>

#include "core/image.h"

namespace brainshift {

enum class SliceAxis { x, y, z };  // sagittal (i fixed), coronal (j fixed), axial (k fixed)

// Grayscale window: the 1st..99th percentile of the whole image. labels may be
// null; otherwise it must share the image's grid. Label colours: 1 green,
// 2 blue, 3 red, 4 yellow, others magenta; blended at 40 % opacity.
void write_png_slice(const std::filesystem::path& path, const ImageF& image,
                     const LabelImage* labels, SliceAxis axis, int index);

}  // namespace brainshift
