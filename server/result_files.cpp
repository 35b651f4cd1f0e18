#include "server/result_files.h"

#include "protocol/media.h"

namespace brainshift::server {
using namespace protocol;

std::string result_file_name(ResultPart part) {
  switch (part) {
    case ResultPart::kDisplacement: return "field.nii.gz";
    case ResultPart::kDisplacementItk: return "field.h5";
    case ResultPart::kWarpedImage: return "warped_image.nii.gz";
    case ResultPart::kWarpedLabels: return "warped_labels.nii.gz";
    case ResultPart::kMetrics: return "metrics.json";
    case ResultPart::kTimings: return "timings.json";
    case ResultPart::kModels: return "";
  }
  return "";
}

std::string model_file_name(Structure s) { return "models/" + std::string(to_string(s)) + ".vtp"; }

std::string result_media_type(const std::string& name, const std::string& bytes) {
  auto ends_with = [&](const char* suffix) {
    const std::string s(suffix);
    return name.size() >= s.size() && name.compare(name.size() - s.size(), s.size(), s) == 0;
  };
  if (ends_with(".nii.gz") || ends_with(".nii")) return media::nifti_frame("x", bytes).media_type;
  if (ends_with(".h5")) return std::string(media::kItkH5);
  if (ends_with(".vtp")) return std::string(media::kVtp);
  return std::string(media::kJson);
}

}  // namespace brainshift::server
