#include "server/result_files.h"

#include "protocol/media.h"
#include "server/case_store.h"

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

ScanResultReply collect_result_frames(const CaseStore& store, const ScanResultRequest& request) {
  ScanResultReply reply;
  reply.scan_id = request.scan_id;
  auto add = [&](const std::string& frame, const std::string& file, const char* why_missing) {
    auto bytes = store.read_result_file(request.scan_id, file);
    if (!bytes) {
      reply.unavailable.push_back({frame, why_missing});
      return;
    }
    const std::string media = result_media_type(file, *bytes);
    reply.frames.push_back(Frame{frame, media, std::move(*bytes)});
  };
  for (ResultPart part : request.parts) {
    if (part != ResultPart::kModels) {
      add(frame_name(part), result_file_name(part),
          part == ResultPart::kWarpedImage ? "the engine wrote no warped image" : "not in this result");
      continue;
    }
    const auto& wanted = request.structures.empty() ? all_structures() : request.structures;
    for (Structure s : wanted)
      add(model_frame_name(s), model_file_name(s), "no model of this structure (label absent from the preop)");
  }
  return reply;
}

}  // namespace brainshift::server
