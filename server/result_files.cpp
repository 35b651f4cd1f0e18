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
    case ResultPart::kReport: return "report.png";
    case ResultPart::kModels: return "";
  }
  return "";
}

std::vector<std::string> stored_file_names(ResultPart part) {
  const std::string name = result_file_name(part);
  const std::string gz = ".nii.gz";
  if (name.size() > gz.size() && name.compare(name.size() - gz.size(), gz.size(), gz) == 0)
    return {name.substr(0, name.size() - 3), name};
  return {name};
}

std::string file_for_frame(const std::string& frame) {
  for (Structure s : all_structures())
    if (frame == model_frame_name(s)) return model_file_name(s);
  for (ResultPart p : {ResultPart::kDisplacement, ResultPart::kDisplacementItk, ResultPart::kWarpedImage,
                       ResultPart::kWarpedLabels, ResultPart::kMetrics, ResultPart::kTimings, ResultPart::kReport})
    if (frame == frame_name(p)) return result_file_name(p);
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
  if (ends_with(".png")) return std::string(media::kPng);
  return std::string(media::kJson);
}

}  // namespace brainshift::server
