#include "server/igtl_catalog.h"

#include <tuple>

#include <igtlImageMessage.h>
#include <spdlog/spdlog.h>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "protocol/events.h"
#include "protocol/result_outputs.h"

namespace brainshift::server {
namespace {

using protocol::ResultPart;

constexpr std::size_t kMaxResultImageBytes = kMaxIgtlImageBytes;
// How far back the store's index is searched for done scans (failed ones between).
constexpr std::size_t kScanLookback = 1000;

std::optional<std::pair<std::string, std::string>> read_part(const CaseStore& store, const std::string& scan_id,
                                                              ResultPart part) {
  return read_result_part(store, scan_id, part);
}

bool has_part(const std::vector<std::string>& files, ResultPart part) {
  for (const auto& name : protocol::stored_file_names(part))
    if (std::find(files.begin(), files.end(), name) != files.end()) return true;
  return false;
}

// Runs decode; a failure becomes a problem named in the STATUS, not a lost result.
template <class Decode>
void try_decode(igtl::ResultContent& r, const std::string& name, Decode decode) {
  try {
    decode();
  } catch (const std::exception& e) {
    spdlog::error("OpenIGTLink: scan {}: {} not sent: {}", r.scan_id, name, e.what());
    r.problems.push_back(name + ": " + e.what());
  }
}

// "scan-000012.image" -> {"scan-000012", "image"}; nullopt for other names.
std::optional<std::pair<std::string, std::string>> split_device(const std::string& device) {
  const auto dot = device.rfind('.');
  if (dot == std::string::npos || dot == 0) return std::nullopt;
  return std::make_pair(device.substr(0, dot), device.substr(dot + 1));
}

// Names the gateway gives ("bs.*", "<scan_id>.*"). Any other name is the
// client's own label, not a device it saw listed (OpenIGTLink's example
// clients send "Client"): like an empty name it asks for any available
// data. A name of ours that is not there gets the null body.
bool is_our_name(const std::string& device) {
  return device.rfind("bs.", 0) == 0 || device.rfind("scan-", 0) == 0;
}

igtl::PackedMessage null_reply(const std::string& type, const std::string& device) {
  return igtl::pack_raw(type, device, "", {});
}

}  // namespace

std::optional<std::pair<std::string, std::string>> read_result_part(const CaseStore& store, const std::string& scan_id,
                                                                    protocol::ResultPart part) {
  for (const auto& name : protocol::stored_file_names(part))
    if (auto bytes = store.read_result_file(scan_id, name)) return std::make_pair(name, std::move(*bytes));
  return std::nullopt;
}

igtl::ResultContent load_igtl_result(const CaseStore& store, const std::string& scan_id, const LabelTable& labels) {
  const auto record = store.find(scan_id);
  if (!record || record->state != StoredScanState::done) throw InputError("scan " + scan_id + " has no result");
  igtl::ResultContent r;
  r.scan_id = scan_id;
  r.client_scan_id = record->client_scan_id;
  r.result = record->result;
  r.finished_at = record->finished_at.value_or(protocol::utc_now());
  if (auto f = read_part(store, scan_id, ResultPart::kDisplacement))
    try_decode(r, f->first, [&] { r.field = vector_image_from_bytes(f->second, f->first, kMaxResultImageBytes); });
  if (auto f = read_part(store, scan_id, ResultPart::kWarpedImage))
    try_decode(r, f->first,
               [&] { r.warped_image = scalar_image_from_bytes(f->second, f->first, kMaxResultImageBytes); });
  if (auto f = read_part(store, scan_id, ResultPart::kWarpedLabels))
    try_decode(r, f->first,
               [&] { r.warped_labels = label_image_from_bytes(f->second, f->first, kMaxResultImageBytes); });
  if (auto f = read_part(store, scan_id, ResultPart::kIntraopLabels))
    try_decode(r, f->first,
               [&] { r.intraop_labels = label_image_from_bytes(f->second, f->first, kMaxResultImageBytes); });
  for (const LabelEntry& e : labels.entries) {
    const std::string name = protocol::model_file_name(e.name);
    if (auto bytes = store.read_result_file(scan_id, name))
      try_decode(r, name, [&] { r.models.emplace_back(short_name_of(e), read_vtp_bytes(*bytes, name)); });
  }
  return r;
}

void IgtlCatalog::remember(const igtl::ResultContent& r) {
  const Grid3* grid = r.warped_labels ? &r.warped_labels->grid
                      : r.field       ? &r.field->grid
                      : r.warped_image ? &r.warped_image->grid
                                       : nullptr;
  if (!grid) return;
  ScanMeta m;
  m.time = igtl::time_stamp_from_iso(r.finished_at);
  m.dims = grid->dims;
  m.field = r.field.has_value();
  m.image = r.warped_image.has_value();
  m.labels = r.warped_labels.has_value();
  m.intraop_labels = r.intraop_labels.has_value();
  meta_[r.scan_id] = m;
}

std::vector<std::string> IgtlCatalog::listed_scans() const {
  std::vector<std::string> out;
  for (const auto& record : store_.list_newest_first(kScanLookback))
    if (record.state == StoredScanState::done && out.size() < kIgtlListedScans) out.push_back(record.scan_id);
  return out;
}

const IgtlCatalog::ScanMeta& IgtlCatalog::meta_of(const std::string& scan_id) {
  if (auto it = meta_.find(scan_id); it != meta_.end()) return it->second;
  const auto record = store_.find(scan_id);
  if (!record || record->state != StoredScanState::done) throw InputError("scan " + scan_id + " has no result");
  const auto files = store_.result_file_names(scan_id);
  ScanMeta m;
  m.time = igtl::time_stamp_from_iso(record->finished_at.value_or(protocol::utc_now()));
  m.field = has_part(files, ResultPart::kDisplacement);
  m.image = has_part(files, ResultPart::kWarpedImage);
  m.labels = has_part(files, ResultPart::kWarpedLabels);
  m.intraop_labels = has_part(files, ResultPart::kIntraopLabels);
  // The three share the intraop grid: the label map is the cheapest to decode.
  const ResultPart smallest = m.labels ? ResultPart::kWarpedLabels
                              : m.image ? ResultPart::kWarpedImage
                                        : ResultPart::kDisplacement;
  const auto f = read_part(store_, scan_id, smallest);
  if (!f) throw InputError("scan " + scan_id + " has no image in the store");
  if (smallest == ResultPart::kWarpedLabels)
    m.dims = label_image_from_bytes(f->second, f->first, kMaxResultImageBytes).grid.dims;
  else if (smallest == ResultPart::kWarpedImage)
    m.dims = scalar_image_from_bytes(f->second, f->first, kMaxResultImageBytes).grid.dims;
  else
    m.dims = vector_image_from_bytes(f->second, f->first, kMaxResultImageBytes).grid.dims;
  return meta_[scan_id] = m;
}

igtl::PackedMessage IgtlCatalog::answer_get(const std::string& type, const std::string& device) {
  try {
    if (type == "IMGMETA") return image_meta(device);
    if (type == "LBMETA") return label_meta(device);
    if (type == "IMAGE") return image(device);
    if (type == "POLYDATA") return polydata(device);
    if (type == "STATUS") return status(device);
  } catch (const std::exception& e) {
    spdlog::error("OpenIGTLink: GET_{} \"{}\": {}", type, device, e.what());
  }
  return null_reply(type, device);  // also a name that cannot be packed (20 characters)
}

igtl::PackedMessage IgtlCatalog::image_meta(const std::string& device) {
  std::vector<igtl::ImageMetaEntry> entries;
  for (const auto& scan : listed_scans()) {
    const ScanMeta& m = meta_of(scan);
    // Float32 both: IMGMETA has no component count (the field has three).
    if (m.image)
      entries.push_back({scan + " warped image", scan + ".image", m.dims, ::igtl::ImageMessage::TYPE_FLOAT32, m.time});
    if (m.field)
      entries.push_back(
          {scan + " displacement field (RAS mm)", scan + ".field", m.dims, ::igtl::ImageMessage::TYPE_FLOAT32, m.time});
  }
  return igtl::pack_image_meta(device, entries, entries.empty() ? igtl::TimeStamp{} : entries.front().time);
}

igtl::PackedMessage IgtlCatalog::label_meta(const std::string& device) {
  // One element per structure of each label map (LBMETA's label value and
  // colour are a structure's), all naming the map's device.
  // The engine's segmentation (of an image pushed alone, or of labels refined
  // by their image) is a label map too.
  std::vector<igtl::LabelMetaEntry> entries;
  for (const auto& scan : listed_scans()) {
    const ScanMeta& m = meta_of(scan);
    const std::string owner = scan + (m.image ? ".image" : ".labels");
    for (const auto& [present, suffix, what] : {std::tuple{m.labels, ".labels", ""},
                                                std::tuple{m.intraop_labels, ".seg", " (segmentation)"}}) {
      if (!present) continue;
      for (const LabelEntry& e : labels_.entries) {
        if (e.value > 255) continue;  // LBMETA's label field is one byte
        entries.push_back({scan + " " + e.name + what, scan + suffix, owner, static_cast<std::uint8_t>(e.value),
                           e.colour, m.dims});
      }
    }
  }
  return igtl::pack_label_meta(device, entries, {});
}

igtl::PackedMessage IgtlCatalog::image(const std::string& device) {
  const auto scans = listed_scans();
  if (scans.empty()) return null_reply("IMAGE", device);
  std::string scan = scans.front(), part = "image";
  if (!is_our_name(device)) {
    if (!meta_of(scan).image) part = "labels";  // any available data
  } else if (device == igtl::kFieldDevice || device == igtl::kWarpedLabelsDevice ||
             device == igtl::kIntraopLabelsDevice) {
    part = device == igtl::kFieldDevice ? "field" : device == igtl::kWarpedLabelsDevice ? "labels" : "seg";
  } else if (device != igtl::kWarpedImageDevice) {
    const auto named = split_device(device);
    if (!named || std::find(scans.begin(), scans.end(), named->first) == scans.end())
      return null_reply("IMAGE", device);
    std::tie(scan, part) = *named;
  }
  const auto t = meta_of(scan).time;
  // The reply is named as the query; an unnamed one names what it holds.
  const std::string reply = device.empty() ? scan + "." + part : device;
  const ResultPart which = part == "field"            ? ResultPart::kDisplacement
                           : part == "labels"         ? ResultPart::kWarpedLabels
                           : part == "seg"            ? ResultPart::kIntraopLabels
                           : part == "image"          ? ResultPart::kWarpedImage
                                                      : ResultPart::kDisplacementItk;
  if (which == ResultPart::kDisplacementItk) return null_reply("IMAGE", device);
  const auto f = read_part(store_, scan, which);
  if (!f) return null_reply("IMAGE", device);
  if (which == ResultPart::kDisplacement)
    return igtl::pack_field(reply, vector_image_from_bytes(f->second, f->first, kMaxResultImageBytes), t);
  if (which == ResultPart::kWarpedLabels || which == ResultPart::kIntraopLabels)
    return igtl::pack_labels(reply, label_image_from_bytes(f->second, f->first, kMaxResultImageBytes), t);
  return igtl::pack_image(reply, scalar_image_from_bytes(f->second, f->first, kMaxResultImageBytes), t);
}

igtl::PackedMessage IgtlCatalog::polydata(const std::string& device) {
  const auto scans = listed_scans();
  if (scans.empty()) return null_reply("POLYDATA", device);
  const auto t = meta_of(scans.front()).time;
  const bool any = !is_our_name(device);
  for (const LabelEntry& e : labels_.entries) {
    const std::string name = protocol::model_file_name(e.name), own = igtl::model_device(short_name_of(e));
    if (!any && device != own) continue;
    if (auto bytes = store_.read_result_file(scans.front(), name))
      return igtl::pack_polydata(device.empty() ? own : device, read_vtp_bytes(*bytes, name), t);
    if (!any) break;
  }
  return null_reply("POLYDATA", device);
}

igtl::PackedMessage IgtlCatalog::status(const std::string& device) {
  const auto scans = listed_scans();
  if (scans.empty()) return null_reply("STATUS", device);
  const auto record = store_.find(scans.front());
  igtl::ResultContent r;
  r.scan_id = record->scan_id;
  r.client_scan_id = record->client_scan_id;
  r.result = record->result;
  r.finished_at = record->finished_at.value_or(protocol::utc_now());
  return igtl::pack_result_status(device.empty() ? igtl::kStatusDevice : device, r);
}

}  // namespace brainshift::server
