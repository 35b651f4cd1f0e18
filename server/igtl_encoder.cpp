#include "server/igtl_encoder.h"

#include <cstdio>
#include <algorithm>
#include <cstring>
#include <ctime>
#include <limits>

#include <igtlImageMessage.h>
#include <igtlImageMetaMessage.h>
#include <igtlLabelMetaMessage.h>
#include <igtlPolyDataMessage.h>
#include <igtlStatusMessage.h>
#include <igtl_header.h>
#include <igtl_util.h>
#include <nlohmann/json.hpp>

#include "core/errors.h"

namespace brainshift::server::igtl {
namespace {

static_assert(sizeof(Eigen::Vector3f) == 3 * sizeof(float), "a field's voxels are copied as packed float triples");

void check_name(const std::string& what, const std::string& name) {
  if (name.size() > kMaxDeviceName)
    throw std::logic_error("OpenIGTLink " + what + " \"" + name + "\" is longer than " +
                           std::to_string(kMaxDeviceName) + " characters");
}

void check_device(const std::string& device) {
  if (device.empty() || device.size() > kMaxDeviceName)
    throw std::logic_error("OpenIGTLink device name \"" + device + "\" must be 1.." +
                           std::to_string(kMaxDeviceName) + " characters");
}

PackedMessage take_pack(::igtl::MessageBase::Pointer message, const std::string& device, const char* type) {
  message->Pack();
  const auto* p = static_cast<const char*>(message->GetPackPointer());
  const std::string_view bytes(p, static_cast<std::size_t>(message->GetPackSize()));
  // The deleter holds a reference to the message, which owns the buffer.
  std::shared_ptr<const void> owner(p, [keep = message](const void*) mutable { keep = nullptr; });
  return PackedMessage{device, type, bytes, std::move(owner)};
}

// The IMAGE geometry: the library stores unit axis directions ("normals"),
// spacing and the position of the volume's centre.
void set_geometry(::igtl::ImageMessage& m, const Grid3& grid, const std::string& device) {
  for (int d : grid.dims)
    if (d < 1 || d > std::numeric_limits<std::uint16_t>::max())
      throw InputError(device + ": " + std::to_string(d) + " voxels along an axis; an OpenIGTLink IMAGE holds 1..65535");
  m.SetDimensions(grid.dims[0], grid.dims[1], grid.dims[2]);
  const Eigen::Vector3d spacing = grid.spacing_mm();
  m.SetSpacing(static_cast<float>(spacing.x()), static_cast<float>(spacing.y()), static_cast<float>(spacing.z()));
  float axes[3][3];  // axes[a] = unit direction of voxel axis a in RAS
  for (int a = 0; a < 3; ++a)
    for (int r = 0; r < 3; ++r) axes[a][r] = static_cast<float>(grid.world_from_voxel(r, a) / spacing[a]);
  m.SetNormals(axes[0], axes[1], axes[2]);
  const Eigen::Vector3d centre =
      grid.world_mm((grid.dims[0] - 1) / 2.0, (grid.dims[1] - 1) / 2.0, (grid.dims[2] - 1) / 2.0);
  m.SetOrigin(static_cast<float>(centre.x()), static_cast<float>(centre.y()), static_cast<float>(centre.z()));
  m.SetCoordinateSystem(::igtl::ImageMessage::COORDINATE_RAS);
}

PackedMessage pack_voxels(const std::string& device, const Grid3& grid, int scalar_type, int components,
                          const void* voxels, std::size_t voxel_bytes, TimeStamp t) {
  check_device(device);
  if (voxel_bytes > static_cast<std::size_t>(std::numeric_limits<int>::max() - 4096))
    throw InputError(device + ": " + std::to_string(voxel_bytes) +
                     " bytes of voxels; an OpenIGTLink message holds less than 2 GiB");
  auto m = ::igtl::ImageMessage::New();
  m->SetDeviceName(device.c_str());
  set_geometry(*m, grid, device);
  m->SetScalarType(scalar_type);
  m->SetNumComponents(components);
  m->SetEndian(igtl_is_little_endian() ? ::igtl::ImageMessage::ENDIAN_LITTLE : ::igtl::ImageMessage::ENDIAN_BIG);
  int dims[3] = {grid.dims[0], grid.dims[1], grid.dims[2]}, offset[3] = {0, 0, 0};
  m->SetSubVolume(dims, offset);
  m->AllocateScalars();
  if (static_cast<std::size_t>(m->GetImageSize()) != voxel_bytes)
    throw std::logic_error(device + ": IMAGE size differs from the voxel buffer");
  std::memcpy(m->GetScalarPointer(), voxels, voxel_bytes);
  m->SetTimeStamp(t.seconds, t.fraction);
  return take_pack(m.GetPointer(), device, "IMAGE");
}

}  // namespace

std::string model_device(const std::string& short_name) {
  const std::string device = "bs.model." + short_name;
  if (device.size() > kMaxDeviceName)
    throw std::invalid_argument("OpenIGTLink: device name \"" + device + "\" exceeds 19 characters");
  return device;
}

TimeStamp time_stamp_from_iso(const std::string& utc) {
  std::tm tm{};
  int millis = 0, consumed = 0;
  const int n = std::sscanf(utc.c_str(), "%4d-%2d-%2dT%2d:%2d:%2d.%3dZ%n", &tm.tm_year, &tm.tm_mon, &tm.tm_mday,
                            &tm.tm_hour, &tm.tm_min, &tm.tm_sec, &millis, &consumed);
  if (n != 7 || consumed != static_cast<int>(utc.size()))
    throw InputError("time \"" + utc + "\" is not ISO-8601 UTC with milliseconds (2024-05-01T12:34:56.789Z)");
  tm.tm_year -= 1900;
  tm.tm_mon -= 1;
  const std::time_t seconds = timegm(&tm);
  if (seconds < 0) throw InputError("time \"" + utc + "\" is before 1970");
  // The fraction is binary: fraction / 2^32 s.
  const auto fraction = static_cast<std::uint32_t>((static_cast<std::uint64_t>(millis) << 32) / 1000);
  return {static_cast<std::uint32_t>(seconds), fraction};
}

PackedMessage pack_field(const std::string& device, const VectorImage3& field_mm, TimeStamp t) {
  return pack_voxels(device, field_mm.grid, ::igtl::ImageMessage::TYPE_FLOAT32, 3, field_mm.vectors.data(),
                     field_mm.vectors.size() * sizeof(Eigen::Vector3f), t);
}

PackedMessage pack_image(const std::string& device, const ImageF& image, TimeStamp t) {
  return pack_voxels(device, image.grid, ::igtl::ImageMessage::TYPE_FLOAT32, 1, image.voxels.data(),
                     image.voxels.size() * sizeof(float), t);
}

PackedMessage pack_labels(const std::string& device, const LabelImage& labels, TimeStamp t) {
  return pack_voxels(device, labels.grid, ::igtl::ImageMessage::TYPE_UINT16, 1, labels.voxels.data(),
                     labels.voxels.size() * sizeof(std::uint16_t), t);
}

PackedMessage pack_polydata(const std::string& device, const TriSurface& surface, TimeStamp t) {
  check_device(device);
  auto m = ::igtl::PolyDataMessage::New();
  m->SetDeviceName(device.c_str());
  auto points = ::igtl::PolyDataPointArray::New();
  for (const Eigen::Vector3d& v : surface.vertices_mm)
    points->AddPoint(static_cast<igtlFloat32>(v.x()), static_cast<igtlFloat32>(v.y()), static_cast<igtlFloat32>(v.z()));
  auto polygons = ::igtl::PolyDataCellArray::New();
  for (const auto& tri : surface.triangles) {
    igtlUint32 ids[3] = {static_cast<igtlUint32>(tri[0]), static_cast<igtlUint32>(tri[1]),
                         static_cast<igtlUint32>(tri[2])};
    polygons->AddCell(3, ids);
  }
  m->SetPoints(points);
  m->SetPolygons(polygons);
  m->SetTimeStamp(t.seconds, t.fraction);
  return take_pack(m.GetPointer(), device, "POLYDATA");
}

PackedMessage pack_status(const std::string& device, int code, std::int64_t subcode, const std::string& error_name,
                          const std::string& text, TimeStamp t) {
  check_device(device);
  check_name("error name", error_name);
  auto m = ::igtl::StatusMessage::New();
  m->SetDeviceName(device.c_str());
  m->SetCode(code);
  m->SetSubCode(subcode);
  m->SetErrorName(error_name.c_str());
  m->SetStatusString(text.c_str());
  m->SetTimeStamp(t.seconds, t.fraction);
  return take_pack(m.GetPointer(), device, "STATUS");
}

namespace {

// The header fields hold 12 (type) and 20 (device) bytes.
void check_reply_names(const std::string& type, const std::string& device) {
  if (type.empty() || type.size() > IGTL_HEADER_TYPE_SIZE || device.size() > IGTL_HEADER_NAME_SIZE)
    throw std::logic_error("OpenIGTLink reply type \"" + type + "\" or device \"" + device + "\" does not fit the header");
}

std::array<igtlUint16, 3> meta_size(const std::array<int, 3>& dims, const std::string& device) {
  std::array<igtlUint16, 3> size{};
  for (int a = 0; a < 3; ++a) {
    if (dims[a] < 1 || dims[a] > std::numeric_limits<std::uint16_t>::max())
      throw InputError(device + ": " + std::to_string(dims[a]) + " voxels along an axis; OpenIGTLink holds 1..65535");
    size[a] = static_cast<igtlUint16>(dims[a]);
  }
  return size;
}

}  // namespace

PackedMessage pack_image_meta(const std::string& device, const std::vector<ImageMetaEntry>& entries, TimeStamp t) {
  check_reply_names("IMGMETA", device);
  auto m = ::igtl::ImageMetaMessage::New();
  m->SetDeviceName(device.c_str());
  for (const ImageMetaEntry& e : entries) {
    auto el = ::igtl::ImageMetaElement::New();
    check_device(e.device);
    el->SetName(e.name.substr(0, 63).c_str());
    el->SetDeviceName(e.device.c_str());
    auto size = meta_size(e.dims, e.device);
    el->SetSize(size.data());
    el->SetScalarType(static_cast<igtlUint8>(e.scalar_type));
    auto ts = ::igtl::TimeStamp::New();
    ts->SetTime(e.time.seconds, igtl_frac_to_nanosec(e.time.fraction));
    el->SetTimeStamp(ts);
    m->AddImageMetaElement(el);
  }
  m->SetTimeStamp(t.seconds, t.fraction);
  return take_pack(m.GetPointer(), device, "IMGMETA");
}

PackedMessage pack_label_meta(const std::string& device, const std::vector<LabelMetaEntry>& entries, TimeStamp t) {
  check_reply_names("LBMETA", device);
  auto m = ::igtl::LabelMetaMessage::New();
  m->SetDeviceName(device.c_str());
  for (const LabelMetaEntry& e : entries) {
    auto el = ::igtl::LabelMetaElement::New();
    check_device(e.device);
    check_device(e.owner);
    el->SetName(e.name.substr(0, 63).c_str());
    el->SetDeviceName(e.device.c_str());
    el->SetOwner(e.owner.c_str());
    el->SetLabel(e.value);
    el->SetRGBA(e.colour[0], e.colour[1], e.colour[2], 255);
    auto size = meta_size(e.dims, e.device);
    el->SetSize(size.data());
    m->AddLabelMetaElement(el);
  }
  m->SetTimeStamp(t.seconds, t.fraction);
  return take_pack(m.GetPointer(), device, "LBMETA");
}

PackedMessage pack_raw(const std::string& type, const std::string& device, std::string body, TimeStamp t) {
  check_reply_names(type, device);
  igtl_header h{};
  h.version = IGTL_HEADER_VERSION;
  std::memcpy(h.name, type.data(), std::min<std::size_t>(type.size(), IGTL_HEADER_TYPE_SIZE));
  std::memcpy(h.device_name, device.data(), std::min<std::size_t>(device.size(), IGTL_HEADER_NAME_SIZE));
  h.timestamp = (static_cast<igtl_uint64>(t.seconds) << 32) | t.fraction;
  h.body_size = body.size();
  h.crc = crc64(reinterpret_cast<unsigned char*>(body.data()), body.size(), 0);
  igtl_header_convert_byte_order(&h);
  auto bytes = std::make_shared<std::string>(reinterpret_cast<const char*>(&h), IGTL_HEADER_SIZE);
  *bytes += body;
  const std::string_view view(*bytes);
  return PackedMessage{device, type, view, std::move(bytes)};
}

std::string status_text(const ResultContent& r) {
  nlohmann::json j{{"scan_id", r.scan_id}, {"kind", std::string(protocol::to_string(r.result.kind))},
                   {"reason", r.result.fallback_reason},
                   {"finished_at", r.finished_at}};
  if (r.client_scan_id) j["client_scan_id"] = *r.client_scan_id;
  if (!r.problems.empty()) j["problems"] = r.problems;
  if (!r.result.caution.empty()) j["caution"] = r.result.caution;
  return j.dump();
}

PackedMessage pack_result_status(const std::string& device, const ResultContent& r) {
  const bool fallback = r.result.kind == protocol::ResultKind::affine_only_fallback;
  // The error name field is 20 bytes, and a receiver reads a name that fills
  // them past the end (libopenigtlink 1.11): "affine_only_fallback" is 20.
  return pack_status(device, ::igtl::StatusMessage::STATUS_OK, fallback ? kAffineFallbackSubcode : kNonrigidSubcode,
                     fallback ? kAffineFallbackName : kNonrigidName, status_text(r), time_stamp_from_iso(r.finished_at));
}

std::vector<PackedMessage> encode_result(const ResultContent& r) {
  const TimeStamp t = time_stamp_from_iso(r.finished_at);
  std::vector<PackedMessage> out;
  ResultContent status = r;  // collects the parts that could not be packed
  auto add = [&](auto pack) {
    try {
      out.push_back(pack());
    } catch (const InputError& e) {
      status.problems.push_back(e.what());
    }
  };
  if (r.field) add([&] { return pack_field(kFieldDevice, *r.field, t); });
  if (r.warped_image) add([&] { return pack_image(kWarpedImageDevice, *r.warped_image, t); });
  if (r.warped_labels)
    add([&] { return pack_labels(kWarpedLabelsDevice, *r.warped_labels, t); });
  if (r.intraop_labels) add([&] { return pack_labels(kIntraopLabelsDevice, *r.intraop_labels, t); });
  for (const auto& [short_name, surface] : r.models)
    add([&] { return pack_polydata(model_device(short_name), surface, t); });
  out.push_back(pack_result_status(kStatusDevice, status));
  return out;
}

}  // namespace brainshift::server::igtl
