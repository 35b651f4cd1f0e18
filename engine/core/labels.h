#pragma once
// The project's default label table. Configurable at the edges (config/,
// protocol); the engine receives explicit values, these are only defaults.
#include <cstdint>

namespace brainshift::labels {
inline constexpr std::uint16_t background = 0;
inline constexpr std::uint16_t brain = 1;
inline constexpr std::uint16_t ventricles = 2;
inline constexpr std::uint16_t corticospinal_tract = 3;
inline constexpr std::uint16_t tumor = 4;
}  // namespace brainshift::labels
