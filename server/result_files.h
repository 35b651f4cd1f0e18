#pragma once
// The mapping between result parts on the wire and the files `brainshift
// register --out` writes, shared by the daemon (serving) and the client
// (`pull` writes the same names).
#include <optional>
#include <string>
#include <vector>

#include "protocol/requests.h"

namespace brainshift::server {

// The name `register --out` gives the part (and `pull` writes): "field.nii.gz",
// "field.h5", "warped_image.nii.gz", "warped_labels.nii.gz", "metrics.json",
// "timings.json", "report.png"; "" for kModels (one file per structure).
std::string result_file_name(protocol::ResultPart part);
// Names the part may have in the daemon's store, preferred first: the daemon
// stores images as plain NIfTI ("field.nii"); stores written before that hold
// "field.nii.gz".
std::vector<std::string> stored_file_names(protocol::ResultPart part);
std::string model_file_name(protocol::Structure s);  // "models/brain.vtp"
// register's name for a received frame ("displacement" -> "field.nii.gz",
// "model.brain" -> "models/brain.vtp"); "" for an unknown frame.
std::string file_for_frame(const std::string& frame_name);
// The media type a frame carrying that file has.
std::string result_media_type(const std::string& file_name, const std::string& bytes);

}  // namespace brainshift::server
