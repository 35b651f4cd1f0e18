#pragma once
// One registration result as OpenIGTLink messages (protocol version 2, packed
// by Debian's libopenigtlink 1.11): what the gateway (igtl_gateway.h) sends
// to 3D Slicer. PROTOCOL.md section 16 is the specification.
//
// Frames: everything is sent in RAS+ mm, the project's world frame, with no
// conversion. 3D Slicer's OpenIGTLinkIF (through OpenIGTLinkIO) takes an
// IMAGE matrix as IJK->RAS and POLYDATA points as RAS, and ignores the IMAGE
// coordinate byte; the byte is still set to RAS (1) for receivers that honour
// it. An IMAGE's matrix origin is the CENTRE of the volume (OpenIGTLink's
// convention), not voxel (0,0,0).
#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "core/image.h"
#include "core/label_colour.h"
#include "core/tet_mesh.h"
#include "protocol/requests.h"

namespace brainshift::server::igtl {

// A header's device name field holds 20 bytes; ours stay shorter, so every
// name is NUL-terminated on the wire.
inline constexpr std::size_t kMaxDeviceName = 19;
inline constexpr const char* kFieldDevice = "bs.field";
inline constexpr const char* kWarpedImageDevice = "bs.warped_image";
inline constexpr const char* kWarpedLabelsDevice = "bs.warped_labels";
// The segmentation the engine made (of an image pushed alone, or of labels
// refined by their image; the intraop_labels part): a label map on the intraop grid, as the warped labels.
inline constexpr const char* kIntraopLabelsDevice = "bs.intraop_labels";
// The uncertainty map (float32 mm, 95 % band radius): made after the answer,
// so it follows the result's STATUS as a message of its own.
inline constexpr const char* kUncertaintyDevice = "bs.uncertainty";
inline constexpr const char* kStatusDevice = "bs.status";
// "bs.model.<short name>": the label table's short name (at most 11
// characters, e.g. "cst" for corticospinal_tract) fits the 20 bytes.
std::string model_device(const std::string& short_name);

// STATUS subcode of the result kind (the code is always OK: both kinds are
// valid results; the fallback is marked, not failed).
inline constexpr std::int64_t kNonrigidSubcode = 0;
inline constexpr std::int64_t kAffineFallbackSubcode = 1;
// The STATUS error name of each kind (at most 19 characters, as device names).
inline constexpr const char* kNonrigidName = "nonrigid";
inline constexpr const char* kAffineFallbackName = "affine_fallback";

// Header time stamp: seconds since 1970 (UTC) and a 32-bit binary fraction.
struct TimeStamp {
  std::uint32_t seconds = 0;
  std::uint32_t fraction = 0;
};
// "2024-05-01T12:34:56.789Z" (the store's finished_at); InputError otherwise.
TimeStamp time_stamp_from_iso(const std::string& utc);

// One packed message, header and body, ready for the socket. The bytes are
// the library's own pack buffer (not copied: a whole-head field is ~130 MB),
// kept alive by owner.
struct PackedMessage {
  std::string device;
  std::string type;         // "IMAGE", "POLYDATA", "STATUS"
  std::string_view bytes;   // 58-byte header + body
  std::shared_ptr<const void> owner;
};

// Images on their grid: dims, spacing, unit axis directions and centre from
// world_from_voxel; voxels x fastest, components innermost. Throws InputError
// when the grid exceeds what an IMAGE can describe (65535 voxels per axis,
// 2 GiB of voxels).
PackedMessage pack_field(const std::string& device, const VectorImage3& field_mm, TimeStamp t);  // float32 x3
PackedMessage pack_image(const std::string& device, const ImageF& image, TimeStamp t);           // float32
PackedMessage pack_labels(const std::string& device, const LabelImage& labels, TimeStamp t);     // uint16
// Triangles as POLYGONS, points in RAS+ mm (float32).
PackedMessage pack_polydata(const std::string& device, const TriSurface& surface, TimeStamp t);
PackedMessage pack_status(const std::string& device, int code, std::int64_t subcode, const std::string& error_name,
                          const std::string& text, TimeStamp t);

// Query replies (PROTOCOL.md 16.6). Their device name is the query's, as the
// protocol asks, so it may be empty or fill all 20 bytes.
struct ImageMetaEntry {
  std::string name;    // description, at most 64 characters
  std::string device;  // the name GET_IMAGE takes
  std::array<int, 3> dims{};
  int scalar_type = 0;  // ::igtl::ImageMessage::TYPE_*
  TimeStamp time;
};
struct LabelMetaEntry {
  std::string name;    // the structure, at most 64 characters
  std::string device;  // the label map's name for GET_IMAGE
  std::string owner;   // the image it belongs to
  std::uint8_t value = 0;
  LabelColour colour{};
  std::array<int, 3> dims{};
};
PackedMessage pack_image_meta(const std::string& device, const std::vector<ImageMetaEntry>& entries, TimeStamp t);
PackedMessage pack_label_meta(const std::string& device, const std::vector<LabelMetaEntry>& entries, TimeStamp t);
// Any type with the given body, packed from the header struct: the
// null-body reply of a GET_ for data that is not there, and RTS_ replies
// (one status byte, 0 = done, as the library's RTS_TDATA).
PackedMessage pack_raw(const std::string& type, const std::string& device, std::string body, TimeStamp t);

// A done scan's result, decoded from the store.
struct ResultContent {
  std::string scan_id;
  std::optional<std::string> client_scan_id;
  protocol::ResultKindInfo result;  // nonrigid, or the fallback and why
  std::string finished_at;      // ISO-8601 UTC: every message's time stamp
  std::optional<VectorImage3> field;
  std::optional<ImageF> warped_image;
  std::optional<LabelImage> warped_labels;
  std::optional<LabelImage> intraop_labels;  // only for a scan pushed as an image alone
  std::vector<std::pair<std::string, TriSurface>> models;  // by short name, in label-table order
  std::vector<std::string> problems;  // parts that could not be decoded (named in the STATUS)
};

// The STATUS text: JSON {"scan_id", "client_scan_id"?, "kind", "reason", "finished_at", "problems"?}.
std::string status_text(const ResultContent& r);

// The STATUS that closes a result (also GET_STATUS's reply).
PackedMessage pack_result_status(const std::string& device, const ResultContent& r);

// Field, warped image, warped labels, the engine's segmentation (when it
// made one), the models (in structure order), then
// the STATUS, which closes the result: a receiver has the whole set when it
// sees it. A part that cannot be packed is left out and named in the STATUS.
std::vector<PackedMessage> encode_result(const ResultContent& r);

}  // namespace brainshift::server::igtl
