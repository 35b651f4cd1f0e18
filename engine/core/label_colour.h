#pragma once
// How a label is drawn (sRGB, 0..255 per channel): the report's contours and
// legend, the Slicer scene's models and colour table. The values and names of
// labels are the label table's (core/label_table.h, from config/labels.toml).
#include <array>
#include <cstdint>

namespace brainshift {
using LabelColour = std::array<std::uint8_t, 3>;
}  // namespace brainshift
