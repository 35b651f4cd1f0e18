#pragma once
// The project's default label table. Configurable at the edges (config/,
// protocol); the engine receives explicit values, these are only defaults.
#include <array>
#include <cstdint>

namespace brainshift {
// How a label is drawn (sRGB, 0..255 per channel): the report's contours and
// legend, the Slicer scene's models and colour table.
using LabelColour = std::array<std::uint8_t, 3>;
}  // namespace brainshift

namespace brainshift::labels {
inline constexpr std::uint16_t background = 0;
inline constexpr std::uint16_t brain = 1;
inline constexpr std::uint16_t ventricles = 2;
inline constexpr std::uint16_t corticospinal_tract = 3;
inline constexpr std::uint16_t tumor = 4;
}  // namespace brainshift::labels
