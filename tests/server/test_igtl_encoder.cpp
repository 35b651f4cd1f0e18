// The OpenIGTLink encoding of a result, checked by unpacking it with the
// library's own message classes (as 3D Slicer does) and against golden bytes.
#include <gtest/gtest.h>

#include <cstring>
#include <set>

#include <nlohmann/json.hpp>

#include <igtlMessageHeader.h>

#include "label_table_file.h"
#include "core/errors.h"
#include "igtl_receiver.h"
#include "server/igtl_encoder.h"

using namespace brainshift;
using namespace brainshift::server;
namespace sigtl = brainshift::server::igtl;

namespace {

// An oblique LAS grid: i runs to the patient's left, j anterior, k superior,
// the whole tilted 20 degrees; anisotropic voxels.
Grid3 oblique_las_grid() {
  Grid3 g;
  g.dims = {7, 5, 4};
  const Eigen::Matrix3d tilt = Eigen::AngleAxisd(0.35, Eigen::Vector3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = tilt * Eigen::Vector3d(-1.25, 0.9, 2.5).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(61.5, -40.25, 12.0);
  return g;
}

// Unpacks packed bytes with the library, as a receiver would.
template <class M>
typename M::Pointer unpack(const sigtl::PackedMessage& p) {
  auto header = ::igtl::MessageHeader::New();
  header->InitPack();
  EXPECT_GE(p.bytes.size(), static_cast<std::size_t>(header->GetPackSize()));
  std::memcpy(header->GetPackPointer(), p.bytes.data(), header->GetPackSize());
  header->Unpack();
  auto m = M::New();
  m->SetMessageHeader(header);
  m->AllocatePack();
  EXPECT_EQ(static_cast<std::size_t>(header->GetPackSize() + m->GetPackBodySize()), p.bytes.size());
  std::memcpy(m->GetPackBodyPointer(), p.bytes.data() + header->GetPackSize(), m->GetPackBodySize());
  EXPECT_TRUE(m->Unpack(1) & ::igtl::MessageHeader::UNPACK_BODY) << "CRC or body";
  EXPECT_EQ(std::string(m->GetDeviceName()), p.device);
  EXPECT_EQ(std::string(m->GetDeviceType()), p.type);
  return m;
}

// CRC-64/ECMA-182 as the OpenIGTLink specification defines it, written
// independently of the library's table.
std::uint64_t crc64(const std::string& bytes) {
  std::uint64_t crc = 0;
  for (unsigned char b : bytes) {
    crc ^= static_cast<std::uint64_t>(b) << 56;
    for (int i = 0; i < 8; ++i) crc = (crc & (1ull << 63)) ? (crc << 1) ^ 0x42F0E1EBA9EA3693ull : crc << 1;
  }
  return crc;
}

std::uint64_t big_endian_u64(const std::string& bytes, std::size_t at) {
  std::uint64_t v = 0;
  for (std::size_t i = 0; i < 8; ++i) v = (v << 8) | static_cast<unsigned char>(bytes[at + i]);
  return v;
}

const sigtl::TimeStamp kT = sigtl::time_stamp_from_iso("2026-12-01T17:30:00.500Z");

void expect_geometry(::igtl::ImageMessage& m, const Grid3& grid) {
  int dims[3];
  m.GetDimensions(dims);
  EXPECT_EQ(dims[0], grid.dims[0]);
  EXPECT_EQ(dims[1], grid.dims[1]);
  EXPECT_EQ(dims[2], grid.dims[2]);
  float spacing[3];
  m.GetSpacing(spacing);
  for (int a = 0; a < 3; ++a) EXPECT_NEAR(spacing[a], grid.spacing_mm()[a], 1e-6);
  ::igtl::Matrix4x4 matrix;
  m.GetMatrix(matrix);
  for (int a = 0; a < 3; ++a)
    for (int r = 0; r < 3; ++r)
      EXPECT_NEAR(matrix[r][a], grid.world_from_voxel(r, a) / grid.spacing_mm()[a], 1e-6) << r << "," << a;
  // The origin is the centre of the volume.
  const Eigen::Vector3d centre = grid.world_mm(3.0, 2.0, 1.5);
  for (int r = 0; r < 3; ++r) EXPECT_NEAR(matrix[r][3], centre[r], 1e-4);
  EXPECT_EQ(m.GetCoordinateSystem(), ::igtl::ImageMessage::COORDINATE_RAS);
  // Slicer's IJK->RAS reproduces the NIfTI world_from_voxel.
  EXPECT_LT((test::igtl_world_from_voxel(m) - grid.world_from_voxel).cwiseAbs().maxCoeff(), 1e-4);
}

}  // namespace

TEST(IgtlEncoder, FieldIsAThreeComponentFloatImageOnTheObliqueGrid) {
  VectorImage3 field(oblique_las_grid());
  for (std::size_t i = 0; i < field.vectors.size(); ++i)
    field.vectors[i] = Eigen::Vector3f(0.25f * i, -0.5f * i, 1.0f + i);
  const auto p = sigtl::pack_field(sigtl::kFieldDevice, field, kT);
  auto m = unpack<::igtl::ImageMessage>(p);
  expect_geometry(*m, field.grid);
  EXPECT_EQ(m->GetScalarType(), ::igtl::ImageMessage::TYPE_FLOAT32);
  EXPECT_EQ(m->GetNumComponents(), 3);
  ASSERT_EQ(static_cast<std::size_t>(m->GetImageSize()), field.vectors.size() * 12);
  const auto* v = static_cast<const float*>(m->GetScalarPointer());
  // Components interleaved per voxel, x fastest, RAS mm as in field.nii.gz.
  for (int k : {0, 3})
    for (int i : {0, 6}) {
      const std::size_t at = field.grid.index(i, 4, k);
      for (int c = 0; c < 3; ++c) EXPECT_EQ(v[3 * at + c], field.vectors[at][c]);
    }
}

TEST(IgtlEncoder, WarpedImageAndLabelsKeepTheirVoxels) {
  ImageF image(oblique_las_grid());
  LabelImage labels(oblique_las_grid());
  for (std::size_t i = 0; i < image.voxels.size(); ++i) {
    image.voxels[i] = 0.5f * static_cast<float>(i) - 7;
    labels.voxels[i] = static_cast<std::uint16_t>(i % 3 == 0 ? 4 : 40000 + i);
  }
  auto mi = unpack<::igtl::ImageMessage>(sigtl::pack_image(sigtl::kWarpedImageDevice, image, kT));
  expect_geometry(*mi, image.grid);
  EXPECT_EQ(mi->GetScalarType(), ::igtl::ImageMessage::TYPE_FLOAT32);
  EXPECT_EQ(mi->GetNumComponents(), 1);
  EXPECT_EQ(std::memcmp(mi->GetScalarPointer(), image.voxels.data(), image.voxels.size() * 4), 0);
  auto ml = unpack<::igtl::ImageMessage>(sigtl::pack_labels(sigtl::kWarpedLabelsDevice, labels, kT));
  expect_geometry(*ml, labels.grid);
  EXPECT_EQ(ml->GetScalarType(), ::igtl::ImageMessage::TYPE_UINT16);
  EXPECT_EQ(std::memcmp(ml->GetScalarPointer(), labels.voxels.data(), labels.voxels.size() * 2), 0);
}

TEST(IgtlEncoder, PolyDataCarriesRasPointsAndTriangles) {
  TriSurface s;
  s.vertices_mm = {{-10.5, 20.25, 3}, {11, -2, 4.5}, {0, 0, -30}, {1, 1, 1}};
  s.triangles = {{0, 1, 2}, {0, 2, 3}};
  auto m = unpack<::igtl::PolyDataMessage>(sigtl::pack_polydata(sigtl::model_device("tumor"), s, kT));
  ASSERT_EQ(m->GetPoints()->GetNumberOfPoints(), 4);
  for (int i = 0; i < 4; ++i) {
    igtlFloat32 p[3];
    m->GetPoints()->GetPoint(i, p);
    for (int c = 0; c < 3; ++c) EXPECT_FLOAT_EQ(p[c], static_cast<float>(s.vertices_mm[i][c]));
  }
  ASSERT_NE(m->GetPolygons(), nullptr);
  ASSERT_EQ(m->GetPolygons()->GetNumberOfCells(), 2u);
  igtlUint32 cell[3];
  m->GetPolygons()->GetCell(1, cell);
  EXPECT_EQ(cell[0], 0u);
  EXPECT_EQ(cell[1], 2u);
  EXPECT_EQ(cell[2], 3u);
}

TEST(IgtlEncoder, StatusNamesScanKindAndReason) {
  sigtl::ResultContent r;
  r.scan_id = "s-000042";
  r.client_scan_id = "or1-case7-scan3";
  r.result = {protocol::ResultKind::affine_only_fallback, "mean surface residual 3.4 mm > 3 mm"};
  r.finished_at = "2026-12-01T17:30:00.500Z";
  const auto messages = sigtl::encode_result(r);
  ASSERT_EQ(messages.size(), 1u);  // nothing but the status without parts
  auto m = unpack<::igtl::StatusMessage>(messages.back());
  EXPECT_EQ(m->GetCode(), ::igtl::StatusMessage::STATUS_OK);
  EXPECT_EQ(m->GetSubCode(), sigtl::kAffineFallbackSubcode);
  EXPECT_EQ(std::string(m->GetErrorName()), "affine_fallback");
  const auto text = nlohmann::json::parse(m->GetStatusString());
  EXPECT_EQ(text.at("scan_id"), "s-000042");
  EXPECT_EQ(text.at("client_scan_id"), "or1-case7-scan3");
  EXPECT_EQ(text.at("kind"), "affine_only_fallback");
  EXPECT_EQ(text.at("reason"), r.result.fallback_reason);
  unsigned sec = 0, frac = 0;
  m->GetTimeStamp(&sec, &frac);
  EXPECT_EQ(sec, kT.seconds);
  EXPECT_EQ(frac, kT.fraction);

  r.result = {protocol::ResultKind::nonrigid, ""};
  auto ok = unpack<::igtl::StatusMessage>(sigtl::encode_result(r).back());
  EXPECT_EQ(ok->GetSubCode(), sigtl::kNonrigidSubcode);
  EXPECT_EQ(std::string(ok->GetErrorName()), "nonrigid");
  EXPECT_FALSE(nlohmann::json::parse(ok->GetStatusString()).contains("caution"));
  // A non-rigid result to be read with care stays non-rigid, its caution in the text.
  r.result = {protocol::ResultKind::nonrigid, "", "brain the given labels lack: 120 ml"};
  auto careful = unpack<::igtl::StatusMessage>(sigtl::encode_result(r).back());
  EXPECT_EQ(careful->GetSubCode(), sigtl::kNonrigidSubcode);
  EXPECT_EQ(nlohmann::json::parse(careful->GetStatusString()).at("caution"), r.result.caution);
}

TEST(IgtlEncoder, ResultOrderEndsWithStatusAndNamesPartsThatCannotBeSent) {
  sigtl::ResultContent r;
  r.scan_id = "s-1";
  r.finished_at = "2026-12-01T17:30:00.000Z";
  r.field = VectorImage3(oblique_las_grid());
  Grid3 too_long;  // 70000 voxels along i: more than an IMAGE can say
  too_long.dims = {70000, 1, 1};
  r.warped_image = ImageF(too_long);
  r.warped_labels = LabelImage(oblique_las_grid());
  TriSurface tri;
  tri.vertices_mm = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  tri.triangles = {{0, 1, 2}};
  r.models = {{"brain", tri}, {"cst", tri}};
  const auto messages = sigtl::encode_result(r);
  std::vector<std::string> devices;
  for (const auto& m : messages) devices.push_back(m.device);
  EXPECT_EQ(devices, (std::vector<std::string>{"bs.field", "bs.warped_labels", "bs.model.brain", "bs.model.cst",
                                               "bs.status"}));
  const auto text = nlohmann::json::parse(unpack<::igtl::StatusMessage>(messages.back())->GetStatusString());
  ASSERT_EQ(text.at("problems").size(), 1u);
  EXPECT_NE(text.at("problems")[0].get<std::string>().find("65535"), std::string::npos) << text.dump();
}

TEST(IgtlEncoder, DeviceNamesAreStableShortAndDistinct) {
  std::set<std::string> names = {sigtl::kFieldDevice, sigtl::kWarpedImageDevice, sigtl::kWarpedLabelsDevice,
                                 sigtl::kIntraopLabelsDevice, sigtl::kUncertaintyDevice, sigtl::kStatusDevice};
  const LabelTable& table = config::default_label_table();
  for (const auto& e : table.entries) names.insert(sigtl::model_device(short_name_of(e)));
  EXPECT_EQ(names.size(), 6 + table.entries.size());
  for (const auto& n : names) EXPECT_LE(n.size(), sigtl::kMaxDeviceName) << n;
  EXPECT_EQ(sigtl::model_device(short_name_of(*table.find("ventricles"))), "bs.model.ventricles");
  EXPECT_EQ(sigtl::model_device(short_name_of(*table.find("corticospinal_tract"))), "bs.model.cst");
  EXPECT_THROW(sigtl::model_device("arcuate_fasc"), std::invalid_argument);  // 21 bytes
  EXPECT_THROW(sigtl::pack_status("brainshift.warped_labels", 1, 0, "", "", kT), std::logic_error);
  // A 20-byte error name would reach the receiver without its NUL.
  EXPECT_THROW(sigtl::pack_status(sigtl::kStatusDevice, 1, 0, "affine_only_fallback", "", kT), std::logic_error);
}

TEST(IgtlEncoder, TimeStampsFromTheStoreClock) {
  const auto t = sigtl::time_stamp_from_iso("1970-01-02T00:00:01.250Z");
  EXPECT_EQ(t.seconds, 86401u);
  EXPECT_EQ(t.fraction, 1u << 30);  // 0.25 s of 2^32
  for (const char* bad : {"", "2026-12-01 17:30:00.500Z", "2026-12-01T17:30:00Z", "2026-12-01T17:30:00.500Zx"})
    EXPECT_THROW(sigtl::time_stamp_from_iso(bad), InputError) << bad;
}

// The 58-byte header of a known message, byte for byte (OpenIGTLink v2
// header, as libopenigtlink 1.11 writes it: header version field 1).
TEST(IgtlEncoder, GoldenStatusHeaderBytes) {
  const auto p = sigtl::pack_status("bs.status", 1, 0, "nonrigid", "{}", sigtl::time_stamp_from_iso("2026-01-02T03:04:05.500Z"));
  ASSERT_GE(p.bytes.size(), 58u);
  const std::string header(p.bytes.substr(0, 58)), body(p.bytes.substr(58));
  // code u16, subcode i64, error name [20], then the NUL-terminated string.
  EXPECT_EQ(body.size(), 2u + 8 + 20 + 3);
  EXPECT_EQ(big_endian_u64(header, 50), crc64(body)) << "CRC-64 of the body";
  const unsigned char golden[58] = {
      0x00, 0x01,                                                                         // version 1
      'S', 'T', 'A', 'T', 'U', 'S', 0, 0, 0, 0, 0, 0,                                     // type, 12 bytes
      'b', 's', '.', 's', 't', 'a', 't', 'u', 's', 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,       // device, 20 bytes
      0x69, 0x57, 0x35, 0xa5, 0x80, 0x00, 0x00, 0x00,  // 2026-01-02T03:04:05 UTC = 0x695735a5 s, .5 s = 0x80000000
      0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x21,  // body size 33
      0xea, 0xda, 0xb8, 0x96, 0xc3, 0x4e, 0xdd, 0x7a};  // CRC-64 of the body
  EXPECT_EQ(header, std::string(reinterpret_cast<const char*>(golden), 58));
  const unsigned char golden_body[33] = {0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 'n', 'o', 'n', 'r', 'i', 'g', 'i',
                                         'd', 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, '{', '}', 0};
  EXPECT_EQ(body, std::string(reinterpret_cast<const char*>(golden_body), 33));
}

// An IMAGE byte for byte: header, the 72-byte image header (big endian:
// version 1, components, scalar type 5 = uint16, endian 2 = little, coord
// 1 = RAS, size, the matrix as i/j/k axes times spacing then the CENTRE,
// sub-volume) and the voxels. Two voxels on an LAS grid: i runs to the left
// (-2 mm), voxel (0,0,0) at (10,20,30), so the centre is (9,20,30).
TEST(IgtlEncoder, GoldenImageBytes) {
  Grid3 g;
  g.dims = {2, 1, 1};
  g.world_from_voxel.topLeftCorner<3, 3>() = Eigen::Vector3d(-2, 1, 3).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(10, 20, 30);
  LabelImage labels(g);
  labels.voxels = {0x0102, 0x0304};
  const auto p = sigtl::pack_labels(sigtl::kWarpedLabelsDevice, labels, sigtl::time_stamp_from_iso("2026-01-02T03:04:05.500Z"));
  const unsigned char golden[58 + 76] = {
      // header: version, "IMAGE", "bs.warped_labels", time stamp, body size 76, CRC-64
      0x00, 0x01, 0x49, 0x4d, 0x41, 0x47, 0x45, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x62, 0x73, 0x2e, 0x77,
      0x61, 0x72, 0x70, 0x65, 0x64, 0x5f, 0x6c, 0x61, 0x62, 0x65, 0x6c, 0x73, 0x00, 0x00, 0x00, 0x00, 0x69, 0x57,
      0x35, 0xa5, 0x80, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x4c, 0xef, 0x4d, 0xe7, 0x43,
      0x9a, 0xac, 0xa0, 0xf8,
      // image header: version 1, 1 component, uint16, little endian, RAS, size 2 1 1
      0x00, 0x01, 0x01, 0x05, 0x02, 0x01, 0x00, 0x02, 0x00, 0x01, 0x00, 0x01,
      // matrix: i = (-2,0,0), j = (0,1,0), k = (0,0,3), centre (9,20,30), float32
      0xc0, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x3f, 0x80,
      0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x40, 0x40, 0x00, 0x00,
      0x41, 0x10, 0x00, 0x00, 0x41, 0xa0, 0x00, 0x00, 0x41, 0xf0, 0x00, 0x00,
      // sub-volume offset 0 0 0, size 2 1 1; then the voxels, little endian
      0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x02, 0x00, 0x01, 0x00, 0x01, 0x02, 0x01, 0x04, 0x03};
  ASSERT_EQ(p.bytes.size(), sizeof golden);
  EXPECT_EQ(std::string(p.bytes), std::string(reinterpret_cast<const char*>(golden), sizeof golden));
  EXPECT_EQ(big_endian_u64(std::string(p.bytes), 50), crc64(std::string(p.bytes.substr(58))));
}
