#pragma once
// The mapping between result parts on the wire and the files `brainshift
// register --out` writes, shared by the daemon (serving) and the client
// (`pull` writes the same names).
#include <optional>
#include <string>
#include <vector>

#include "protocol/requests.h"

namespace brainshift::server {

// "field.nii.gz", "field.h5", "warped_image.nii.gz", "warped_labels.nii.gz",
// "metrics.json", "timings.json"; "" for kModels (one file per structure).
std::string result_file_name(protocol::ResultPart part);
std::string model_file_name(protocol::Structure s);  // "models/brain.vtp"
// The media type a frame carrying that file has.
std::string result_media_type(const std::string& file_name, const std::string& bytes);

}  // namespace brainshift::server
