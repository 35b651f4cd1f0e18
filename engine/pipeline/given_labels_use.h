#pragma once
// How labels pushed with their image are used (docs/DESIGN.md "Labels with
// their image"; AutoSegmentationParameters::given_labels, the push's
// labels_use). Header only and free of the engine's dependencies: the
// daemon's core carries a push's choice to the engine.
#include <optional>
#include <string_view>

namespace brainshift {

// refine: the image is classified under the preop the labels' pass carried
// and that segmentation is registered; exact: the labels as given.
enum class GivenLabelsUse { exact, refine };

inline std::string_view to_string(GivenLabelsUse use) { return use == GivenLabelsUse::exact ? "exact" : "refine"; }

inline std::optional<GivenLabelsUse> given_labels_use_from_string(std::string_view name) {
  if (name == "exact") return GivenLabelsUse::exact;
  if (name == "refine") return GivenLabelsUse::refine;
  return std::nullopt;
}

}  // namespace brainshift
