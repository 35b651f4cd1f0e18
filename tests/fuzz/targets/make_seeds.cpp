// Writes the committed seed corpora (tests/fuzz/corpus/<target>/): valid
// messages of every type and valid small NIfTI files, plus the edge cases the
// issue lists. Run by hand when the protocol or the format changes:
//   make_seeds <corpus dir>
// The fuzzers' own finds are never committed wholesale, only regression seeds.
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>

#include "image/nifti_io.h"
#include "test_util.h"  // tests/image: NIfTI-2 from the nifti2.h layout
#include "protocol/events.h"
#include "protocol/media.h"
#include "protocol/requests.h"
#include "wire_split.h"

namespace fs = std::filesystem;
using namespace brainshift;
using namespace brainshift::protocol;

namespace {

fs::path g_dir;

void save(const std::string& target, const std::string& name, const std::string& bytes) {
  fs::create_directories(g_dir / target);
  std::ofstream(g_dir / target / name, std::ios::binary) << bytes;
}

void save_message(const std::string& name, const Message& m) {
  save("message", name, fuzz::join_frames(encode(m)));
}
void save_wire(const std::string& name, const std::vector<std::string>& wire) {
  save("message", name, fuzz::join_frames(wire));
}

// A 4x4x3 head: brain (1) around a ventricle (2), a tumour voxel (4).
LabelImage small_labels() {
  Grid3 g;
  g.dims = {4, 4, 3};
  g.world_from_voxel.diagonal().head<3>() << 2.0, 2.0, 3.0;
  g.world_from_voxel.topRightCorner<3, 1>() << -4.0, -4.0, -3.0;
  LabelImage l(g, 1);
  l.at(0, 0, 0) = 0;
  l.at(1, 1, 1) = 2;
  l.at(2, 2, 1) = 4;
  return l;
}

ImageF small_image() {
  ImageF img(small_labels().grid);
  for (std::size_t i = 0; i < img.voxels.size(); ++i) img.voxels[i] = 10.0f * static_cast<float>(i % 7);
  return img;
}

VectorImage3 small_field() {
  VectorImage3 f(small_labels().grid);
  for (std::size_t i = 0; i < f.vectors.size(); ++i) f.vectors[i] = Eigen::Vector3f(0.5f, -0.25f, float(i % 3));
  return f;
}

template <class T>
void poke(std::string& bytes, std::size_t offset, T value) {
  std::memcpy(bytes.data() + offset, &value, sizeof(T));
}

// Header offsets (nifti1.h).
constexpr std::size_t kDim = 40, kDatatype = 70, kBitpix = 72, kPixdim = 76, kVoxOffset = 108,
                      kSclSlope = 112, kQformCode = 252, kSformCode = 254, kSrowX = 280, kMagic = 344;

// NIfTI-2 versions of valid seeds and its own header defects.
void nifti2_seeds(const std::string& labels) {
  auto as_nifti2 = [](const std::string& n1) { return test::nifti2_file(test::nifti2_header_of(n1), test::nifti1_voxels(n1)); };
  save("nifti", "nifti2_labels_u8.nii", as_nifti2(labels));
  save("nifti", "nifti2_image_f32.nii.gz", test::gzip(as_nifti2(scalar_image_to_bytes(small_image(), VoxelType::float32, false))));
  save("nifti", "nifti2_field_5d.nii", as_nifti2(displacement_field_to_bytes(small_field(), false)));
  nifti_2_header h = test::nifti2_header_of(labels);
  h.magic[4] = '\n';
  save("nifti", "edge_nifti2_damaged_magic.nii", test::nifti2_file(h, test::nifti1_voxels(labels)));
  h = test::nifti2_header_of(labels);
  h.dim[1] = std::int64_t{1} << 40;
  save("nifti", "edge_nifti2_huge_dim.nii", test::nifti2_file(h, test::nifti1_voxels(labels)));
  save("nifti", "edge_nifti2_truncated_header.nii", as_nifti2(labels).substr(0, 400));
}

void nifti_seeds() {
  const std::string labels = label_image_to_bytes(small_labels(), false);
  save("nifti", "labels_u8.nii", labels);
  save("nifti", "labels_u8.nii.gz", label_image_to_bytes(small_labels(), true));
  save("nifti", "image_f32.nii", scalar_image_to_bytes(small_image(), VoxelType::float32, false));
  save("nifti", "image_i16_scaled.nii.gz", scalar_image_to_bytes(small_image(), VoxelType::int16, true));
  save("nifti", "field_5d.nii", displacement_field_to_bytes(small_field(), false));

  std::string qform_only = labels;  // geometry from the quaternion
  poke<std::int16_t>(qform_only, kSformCode, 0);
  save("nifti", "labels_qform_only.nii", qform_only);
  std::string no_xform = qform_only;  // ANALYZE-style: pixdim only
  poke<std::int16_t>(no_xform, kQformCode, 0);
  save("nifti", "labels_no_xform.nii", no_xform);

  std::string swapped = labels;  // big-endian header
  for (std::size_t off : {std::size_t{0}}) std::reverse(swapped.begin() + off, swapped.begin() + off + 4);
  save("nifti", "edge_bad_byte_order.nii", swapped);
  save("nifti", "edge_truncated_header.nii", labels.substr(0, 200));
  save("nifti", "edge_truncated_data.nii", labels.substr(0, labels.size() - 10));
  std::string four_d = labels;
  poke<std::int16_t>(four_d, kDim, 4);
  poke<std::int16_t>(four_d, kDim + 8, 2);
  save("nifti", "edge_4d.nii", four_d);
  std::string zero = labels;
  poke<std::int16_t>(zero, kDim + 4, 0);
  save("nifti", "edge_zero_dim.nii", zero);
  std::string bomb = labels;  // claims 30000^3 voxels: refused before allocation
  for (int d = 1; d <= 3; ++d) poke<std::int16_t>(bomb, kDim + 2 * d, 30000);
  save("nifti", "edge_bomb_header.nii", bomb);
  std::string huge_voxel = labels;
  poke<float>(huge_voxel, kSrowX, 1e6f);
  save("nifti", "edge_absurd_voxel_size.nii", huge_voxel);
  std::string singular = labels;  // x and y axes collinear
  poke<float>(singular, kSrowX + 16, 2.0f);
  poke<float>(singular, kSrowX + 20, 0.0f);
  save("nifti", "edge_singular_affine.nii", singular);
  std::string nan_image = scalar_image_to_bytes(small_image(), VoxelType::float32, false);
  poke<float>(nan_image, 352 + 8, std::numeric_limits<float>::quiet_NaN());
  save("nifti", "edge_nan_voxel.nii", nan_image);
  std::string nan_slope = labels;
  poke<float>(nan_slope, kSclSlope, std::numeric_limits<float>::infinity());
  save("nifti", "edge_inf_slope.nii", nan_slope);
  std::string bad_type = labels;
  poke<std::int16_t>(bad_type, kDatatype, 128);  // RGB24: unsupported
  poke<std::int16_t>(bad_type, kBitpix, 24);
  save("nifti", "edge_rgb_datatype.nii", bad_type);
  std::string offset = labels;
  poke<float>(offset, kVoxOffset, 1e8f);
  save("nifti", "edge_far_vox_offset.nii", offset);
  std::string two_file = labels;
  std::memcpy(two_file.data() + kMagic, "ni1", 4);
  save("nifti", "edge_two_file_magic.nii", two_file);
  std::string pixdim = no_xform;
  poke<float>(pixdim, kPixdim + 4, -1.0f);
  save("nifti", "edge_negative_pixdim.nii", pixdim);
  const std::string gz = label_image_to_bytes(small_labels(), true);
  save("nifti", "edge_gzip_truncated.nii.gz", gz.substr(0, gz.size() / 2));
  std::string corrupt = gz;
  corrupt[gz.size() / 2] ^= 0x55;
  save("nifti", "edge_gzip_corrupt.nii.gz", corrupt);
  save("nifti", "edge_gzip_two_members.nii.gz", gz + gz);
  nifti2_seeds(labels);
}

Frame nifti(const std::string& name, const std::string& bytes) { return media::nifti_frame(name, bytes); }

void message_seeds() {
  const std::string labels_gz = label_image_to_bytes(small_labels(), true);
  const std::string image_gz = scalar_image_to_bytes(small_image(), VoxelType::uint8, true);
  const std::string table = make_label_map_json({{{"brain", {1}}, {"ventricles", {2}},
                                                    {"tumor", {4}}}});
  // Requests.
  save_message("req_status", make_status_request("s-1"));
  save_message("req_preop_load_atlas", make_preop_load_request("p-1", {true, {}, {}, {}}));
  save_message("req_preop_load_upload",
               make_preop_load_request("p-2", {false, nifti("t1", image_gz), nifti("labels", labels_gz),
                                               media::json_frame("label_table", table)}));
  save_message("req_scan_push", make_scan_push_request("u-1", {nifti("labels", labels_gz), nifti("image", image_gz),
                                                               std::string("or1-case42-scan3")}));
  save_message("req_scan_push_plain_nii",
               make_scan_push_request("u-2", {nifti("labels", label_image_to_bytes(small_labels(), false)), {}, {}}));
  save_message("req_scan_result",
               make_scan_result_request("r-1", {"scan-000001",
                                                {ResultPart::kDisplacement, ResultPart::kModels, ResultPart::kTimings},
                                                {"brain", "tumor"}}));
  save_message("req_scan_list", make_scan_list_request("l-1", {10}));
  save_message("req_shutdown", make_shutdown_request("x-1", {"end of case"}));

  // Replies.
  StatusReply status;
  status.state = ServerState::kLoadingPreop;
  status.progress = Progress{"mesh", 0.4};
  status.versions = {{"brainshift", "0.1.0"}};
  status.preop_id = "preop-1";
  status.mesh = MeshSize{100, 400};
  status.mpi_ranks = 2;
  status.queue = {1, 3};
  status.current_scan_id = "scan-000002";
  status.last_error = ErrorInfo{ErrorCode::kInvalidRequest, "labels: empty brain"};
  save_message("rep_status", make_status_reply("s-1", status));
  save_message("rep_preop_load", make_preop_load_reply("p-1", {"preop-1"}));
  save_message("rep_scan_push", make_scan_push_reply("u-1", {"scan-000001", true}));
  ScanResultReply result;
  result.scan_id = "scan-000001";
  result.frames = {media::json_frame("metrics", R"({"min_jacobian":0.5,"folded_voxels":0})"),
                   media::json_frame("timings", make_timings_json({}))};
  result.unavailable = {{"report", "being rendered", true}, {"model.tumor", "no tumour", false}};
  save_message("rep_scan_result", make_scan_result_reply("r-1", result));
  ScanListReply list;
  list.scans = {{"scan-000002", std::string("c-2"), ScanState::kFailed, "2024-05-01T12:00:00.000Z",
                 std::string("2024-05-01T12:00:01.000Z"), {}, ErrorInfo{ErrorCode::kScanFailed, "solver"}},
                {"scan-000001", {}, ScanState::kProcessing, "2024-05-01T11:00:00.000Z", {}, std::string("affine"), {}}};
  save_message("rep_scan_list", make_scan_list_reply("l-1", list));
  save_message("rep_shutdown", make_shutdown_reply("x-1"));
  save_message("rep_error", make_error_reply("u-1", ErrorCode::kBusy, "queue full"));

  // Events.
  save_message("ev_preop_progress", make_event(PreopProgressEvent{"preop-1", "mesh", 0.5}));
  save_message("ev_preop_ready", make_event(PreopReadyEvent{"preop-1", {100, 400}, 12.5}));
  save_message("ev_preop_failed", make_event(PreopFailedEvent{"preop-1", {ErrorCode::kInvalidRequest, "grids"}}));
  save_message("ev_stage", make_event(StageEvent{{StageScope::kIntraop, "scan-000001", "preop-1", "affine", 0.12,
                                                  "2024-05-01T12:34:56.789Z"}}));
  save_message("ev_scan_progress", make_event(ScanProgressEvent{"scan-000001", "solve", 0.7}));
  save_message("ev_scan_done", make_event(ScanDoneEvent{"scan-000001", std::string("c-1"), 1.25}));
  save_message("ev_scan_failed",
               make_event(ScanFailedEvent{"scan-000001", {}, "surface", {ErrorCode::kScanFailed, "diverged"}}));
  save_message("ev_shutdown", make_event(ServerShutdownEvent{"signal"}));

  // Bad input (PROTOCOL.md section 7), one seed per error path.
  const std::string push = R"({"v":1,"type":"scan.push","request_id":"b-1","frames":[{"name":"labels","media_type":"application/x-nifti-1+gzip","size":)" +
                           std::to_string(labels_gz.size()) + "}]}";
  save_wire("bad_version_2", {R"({"v":2,"type":"status","request_id":"b-1"})"});
  save_wire("bad_version_missing", {R"({"type":"status","request_id":"b-1"})"});
  save_wire("bad_version_string", {R"({"v":"1","type":"status","request_id":"b-1"})"});
  save_wire("bad_unknown_type", {R"({"v":1,"type":"scan.delete","request_id":"b-1"})"});
  save_wire("bad_reply_as_request", {R"({"v":1,"type":"status.reply","request_id":"b-1"})"});
  save_wire("bad_json", {R"({"v":1,"type":"status","request_id":)"});
  save_wire("bad_json_array", {R"([1,2,3])"});
  save_wire("bad_request_id_space", {R"({"v":1,"type":"status","request_id":"a b"})"});
  save_wire("bad_request_id_missing", {R"({"v":1,"type":"status"})"});
  save_wire("bad_missing_frame", {push});
  save_wire("bad_extra_frame", {push, labels_gz, image_gz});
  save_wire("bad_size_mismatch", {push, labels_gz.substr(1)});
  save_wire("bad_claims_more_than_sent",
            {R"({"v":1,"type":"scan.push","request_id":"b-1","frames":[{"name":"labels","media_type":"application/x-nifti-1+gzip","size":18446744073709551615}]})",
             labels_gz});
  save_wire("bad_negative_size",
            {R"({"v":1,"type":"scan.push","request_id":"b-1","frames":[{"name":"labels","media_type":"application/x-nifti-1","size":-1}]})",
             ""});
  save_wire("bad_duplicate_frame_name",
            {R"({"v":1,"type":"scan.push","request_id":"b-1","frames":[{"name":"labels","media_type":"application/x-nifti-1+gzip","size":2},{"name":"labels","media_type":"application/x-nifti-1+gzip","size":2}]})",
             "\x1f\x8b", "\x1f\x8b"});
  save_wire("bad_undeclared_extra_frame_name",
            {R"({"v":1,"type":"scan.push","request_id":"b-1","frames":[{"name":"labels","media_type":"application/x-nifti-1+gzip","size":2},{"name":"extra","media_type":"application/json","size":2}]})",
             "\x1f\x8b", "{}"});
  save_wire("bad_media_content",
            {R"({"v":1,"type":"scan.push","request_id":"b-1","frames":[{"name":"labels","media_type":"application/x-nifti-1","size":4}]})",
             "nope"});
  const std::string bad_table = R"({"v":1,"structures":{"brain":[0,70000]}})";
  save_wire("bad_label_table",
            {R"({"v":1,"type":"preop.load","request_id":"b-1","frames":[{"name":"t1","media_type":"application/x-nifti-1+gzip","size":2},{"name":"labels","media_type":"application/x-nifti-1+gzip","size":2},{"name":"label_table","media_type":"application/json","size":)" +
                 std::to_string(bad_table.size()) + "}]}",
             "\x1f\x8b", "\x1f\x8b", bad_table});
  save_wire("bad_parts", {R"({"v":1,"type":"scan.result","request_id":"b-1","scan_id":"s","parts":["models","models",[[["x"]]]]})"});
  save_wire("bad_list_limit", {R"({"v":1,"type":"scan.list","request_id":"b-1","limit":1e300})"});
  save_wire("bad_deep_nesting", {R"({"v":1,"type":"status","request_id":"b-1","x":)" + std::string(2000, '[') +
                                 std::string(2000, ']') + "}"});
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: make_seeds <corpus dir>\n");
    return 2;
  }
  g_dir = argv[1];
  nifti_seeds();
  message_seeds();
  return 0;
}
