#include "protocol/result_outputs.h"

#include <stdexcept>

#include "protocol/media.h"

namespace brainshift::protocol {
namespace {

constexpr std::string_view kModelFramePrefix = "model.";
constexpr std::string_view kModelFilePrefix = "models/";
constexpr std::string_view kModelFileSuffix = ".vtp";

bool starts_with(std::string_view s, std::string_view prefix) { return s.substr(0, prefix.size()) == prefix; }
bool ends_with(std::string_view s, std::string_view suffix) {
  return s.size() >= suffix.size() && s.substr(s.size() - suffix.size()) == suffix;
}

}  // namespace

const ResultOutput& result_output(ResultPart part) {
  for (const auto& o : kResultOutputs)
    if (o.part == part) return o;
  throw std::logic_error("result part without a row in kResultOutputs");
}

std::string_view to_string(ResultPart p) { return result_output(p).wire; }

std::optional<ResultPart> result_part_from_string(std::string_view wire) {
  for (const auto& o : kResultOutputs)
    if (o.wire == wire) return o.part;
  return std::nullopt;
}

std::optional<ResultPart> result_part_from_cli(std::string_view cli) {
  for (const auto& o : kResultOutputs)
    if (o.cli == cli) return o.part;
  return std::nullopt;
}

bool part_expected(ResultPart part, const ScanFacts& scan) { return why_not_expected(part, scan).empty(); }

std::string_view why_not_expected(ResultPart part, const ScanFacts& scan) {
  switch (result_output(part).presence) {
    case PartPresence::kEveryScan: return "";
    case PartPresence::kWithIntraopImage: return scan.has_image ? "" : "no intraop image was pushed";
    case PartPresence::kEngineSegmentation:
      if (!scan.has_image) return "no intraop image was pushed (only a segmentation the engine made is a result part)";
      return scan.has_labels && scan.labels_exact
                 ? "intraop labels were pushed with labels_use \"exact\" (only a segmentation the engine made is a "
                   "result part)"
                 : "";
  }
  return "";
}

std::string frame_name(ResultPart part) {
  if (part == ResultPart::kModels)
    throw std::invalid_argument("frame_name: models travel as model.<structure> frames");
  return std::string(to_string(part));
}

std::vector<std::string> stored_file_names(ResultPart part) {
  const ResultOutput& o = result_output(part);
  if (o.stored == o.file) return {std::string(o.file)};
  return {std::string(o.stored), std::string(o.file)};
}

bool is_valid_structure_name(std::string_view name) {
  if (name.empty() || name.size() > 64 || name[0] < 'a' || name[0] > 'z') return false;
  for (char c : name)
    if (!((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_')) return false;
  return true;
}

std::string model_frame_name(std::string_view structure) {
  return std::string(kModelFramePrefix) + std::string(structure);
}

std::string model_file_name(std::string_view structure) {
  return std::string(kModelFilePrefix) + std::string(structure) + std::string(kModelFileSuffix);
}

std::optional<std::string> structure_of_model_frame(std::string_view frame) {
  if (!starts_with(frame, kModelFramePrefix)) return std::nullopt;
  const std::string_view name = frame.substr(kModelFramePrefix.size());
  if (!is_valid_structure_name(name)) return std::nullopt;
  return std::string(name);
}

std::optional<std::string> structure_of_model_file(std::string_view file) {
  if (!starts_with(file, kModelFilePrefix) || !ends_with(file, kModelFileSuffix)) return std::nullopt;
  const std::string_view name =
      file.substr(kModelFilePrefix.size(), file.size() - kModelFilePrefix.size() - kModelFileSuffix.size());
  if (!is_valid_structure_name(name)) return std::nullopt;
  return std::string(name);
}

std::string file_for_frame(std::string_view frame) {
  if (const auto s = structure_of_model_frame(frame)) return model_file_name(*s);
  const auto part = result_part_from_string(frame);
  if (!part || *part == ResultPart::kModels) return "";
  return std::string(result_output(*part).file);
}

std::optional<ResultPart> part_of_file(std::string_view file) {
  if (structure_of_model_file(file)) return ResultPart::kModels;
  for (const auto& o : kResultOutputs)
    if (o.part != ResultPart::kModels && (o.file == file || o.stored == file)) return o.part;
  return std::nullopt;
}

bool media_type_fits(ResultPart part, std::string_view media_type) {
  switch (result_output(part).media) {
    case MediaKind::kNifti: return media::is_nifti(media_type);
    case MediaKind::kItkH5: return media_type == media::kItkH5;
    case MediaKind::kVtp: return media_type == media::kVtp;
    case MediaKind::kJson: return media_type == media::kJson;
    case MediaKind::kPng: return media_type == media::kPng;
  }
  return false;
}

std::string result_media_type(std::string_view file, std::string_view bytes) {
  const auto part = part_of_file(file);
  if (!part) throw std::invalid_argument("result_media_type: \"" + std::string(file) + "\" is no result file");
  switch (result_output(*part).media) {
    case MediaKind::kNifti: return std::string(media::nifti_media_type(bytes));
    case MediaKind::kItkH5: return std::string(media::kItkH5);
    case MediaKind::kVtp: return std::string(media::kVtp);
    case MediaKind::kJson: return std::string(media::kJson);
    case MediaKind::kPng: return std::string(media::kPng);
  }
  return std::string(media::kJson);
}

}  // namespace brainshift::protocol
