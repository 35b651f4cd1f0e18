#pragma once
// The label table of a labels.toml as the Slicer scene needs it (names,
// colours, which label is the parenchyma): NetworkOptions::scene_labels of
// brainshift-offline, which links the configuration reader.
#include <string>
#include <vector>

#include "slicer_scene.h"

namespace brainshift::cli {

// toml_file "" = the shipped labels.toml. CommandError(kExitUsage) when the
// file cannot be read or is not a valid label table.
std::vector<SceneLabel> scene_labels_from_toml(const std::string& toml_file);

}  // namespace brainshift::cli
