#pragma once
// A 3D Slicer scene (.mrml, MRML XML) over a pulled result folder, so that one
// File > Open shows everything in the right frame:
//
//   field.h5            GridTransform "brainshift field". ITK's (and so
//                       Slicer's) transform files hold the resampling
//                       direction, fixed -> moving: here intraop -> preop,
//                       our pull-back. Slicer takes it as the transform "from
//                       parent": a volume under it is resampled from its own
//                       (preop) frame into the world (intraop) frame.
//   preop image         Volume under that transform, when one is given: it
//                       shows aligned with the intraop scan.
//   intraop image       Volume, no transform (the world frame), when given.
//   warped_image.nii.gz Volume, no transform: already on the intraop grid.
//   warped_labels.nii.gz LabelMapVolume with the label table as its colour
//                       table (labels.ctbl, written beside the scene).
//   models/<name>.vtp   Model per structure, no transform (carried into the
//                       intraop frame already), colour from the label table;
//                       their storage nodes declare coordinateSystem="RAS",
//                       as the files' SPACE field does.
//
// File names in the scene are relative to its folder, so the folder can be
// moved or copied as a whole.
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "core/label_colour.h"

namespace brainshift::cli {

struct SceneLabel {
  std::uint16_t value = 0;
  std::string name;    // model file models/<name>.vtp when it has one
  LabelColour colour{};
  bool outer = false;  // the brain surface: drawn see-through so inner models show
};

struct SceneContents {
  // Relative to the scene's folder; every file must exist there.
  std::optional<std::string> preop_image;    // e.g. "preop_t1.nii.gz"
  std::optional<std::string> intraop_image;  // e.g. "intraop_t1.nii.gz"
  std::vector<SceneLabel> labels;            // the label table, in table order
  // pull --format nrrd: the scene loads field.nrrd (a Slicer grid transform),
  // warped_image.nrrd and warped_labels.nrrd instead of field.h5 and the NIfTI files.
  bool nrrd = false;
};

inline constexpr const char* kSceneFile = "scene.mrml";
inline constexpr const char* kSceneColourTable = "labels.ctbl";

// Writes DIR/scene.mrml and DIR/labels.ctbl. DIR must hold field.h5,
// warped_image.nii.gz and warped_labels.nii.gz; a model is listed for each
// label whose models/<name>.vtp exists. Throws std::runtime_error naming a
// missing file or an unwritable path.
void write_slicer_scene(const std::filesystem::path& dir, const SceneContents& contents);

}  // namespace brainshift::cli
