#pragma once
// What the OpenIGTLink gateway reads from the store: a done scan's whole
// result for the pushes (load_igtl_result), and the answers to the queries
// 3D Slicer's OpenIGTLink Remote sends (GET_IMGMETA, GET_LBMETA, GET_IMAGE,
// GET_POLYDATA, GET_STATUS). PROTOCOL.md section 16.6.
//
// Devices of the newest kIgtlListedScans done scans: "<scan_id>.image"
// (warped image), "<scan_id>.field", "<scan_id>.labels" (warped labels),
// "<scan_id>.seg" (the engine's segmentation of an image alone: the header's
// 20 bytes leave 7 characters after the scan id);
// the pushed names (bs.field, bs.warped_image, bs.warped_labels, bs.intraop_labels,
// bs.model.<short name>, bs.status) name the newest done scan's parts.
// Used by the gateway thread only (not thread-safe).
#include <array>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "core/label_table.h"
#include "protocol/result_outputs.h"
#include "server/case_store.h"
#include "server/igtl_encoder.h"

namespace brainshift::server {

// Our own outputs: bounded only so that a corrupt header cannot ask for more.
inline constexpr std::size_t kMaxIgtlImageBytes = std::size_t{4} << 30;

// A stored part's file name and bytes (the first of its stored names
// present); nullopt when the scan has none.
std::optional<std::pair<std::string, std::string>> read_result_part(const CaseStore& store, const std::string& scan_id,
                                                                    protocol::ResultPart part);

// A done scan's result read back from the store; unreadable parts are left
// out and named in problems. labels names the models' devices (their short names).
igtl::ResultContent load_igtl_result(const CaseStore& store, const std::string& scan_id, const LabelTable& labels);

// How many done scans the meta lists show: an operation has a handful of
// intraop scans; older ones stay reachable by scan.pull on the request socket.
inline constexpr std::size_t kIgtlListedScans = 16;

class IgtlCatalog {
 public:
  IgtlCatalog(const CaseStore& store, const LabelTable& labels) : store_(store), labels_(labels) {}
  // The reply to a GET_<type> query (type without the prefix): one message
  // of that type named as the query. Data that is not there gets a
  // null-body reply, as the protocol asks; an empty name asks for the
  // newest scan's (image: warped image; polydata: first model).
  igtl::PackedMessage answer_get(const std::string& type, const std::string& device);
  // Remembers a decoded result's grid, so its meta needs no store read.
  void remember(const igtl::ResultContent& r);

 private:
  struct ScanMeta {
    igtl::TimeStamp time;
    std::array<int, 3> dims{};  // field, image and labels share the intraop grid
    bool field = false, image = false, labels = false;
    bool intraop_labels = false;  // the engine's segmentation (an image alone, or labels refined by it)
  };
  std::vector<std::string> listed_scans() const;  // done, newest first
  const ScanMeta& meta_of(const std::string& scan_id);
  igtl::PackedMessage image_meta(const std::string& device);
  igtl::PackedMessage label_meta(const std::string& device);
  igtl::PackedMessage image(const std::string& device);
  igtl::PackedMessage polydata(const std::string& device);
  igtl::PackedMessage status(const std::string& device);

  const CaseStore& store_;
  const LabelTable& labels_;
  std::map<std::string, ScanMeta> meta_;  // results never change once done
};

}  // namespace brainshift::server
