// Sizes and counts from the wire are bounded before use (PROTOCOL.md 13.5):
// each bound is refused with its typed error one step past the limit and
// accepted at it.
#include <gtest/gtest.h>

#include "protocol/media.h"
#include "protocol/requests.h"
#include "test_util.h"

namespace bp = brainshift::protocol;
using bp::ErrorCode;
using nlohmann::json;

namespace {

using bp::testing::error_of;

std::vector<std::string> status_wire_with_manifest(std::size_t entries) {
  json header = {{"v", 1}, {"type", "status"}, {"request_id", "m"}, {"frames", json::array()}};
  for (std::size_t i = 0; i < entries; ++i)
    header["frames"].push_back({{"name", "f" + std::to_string(i)}, {"media_type", "application/json"}, {"size", 0}});
  return {header.dump()};
}

TEST(WireBounds, ManifestLongerThanTheFrameLimitIsTooLargeBeforeItsEntriesAreRead) {
  const bp::Limits limits;
  EXPECT_EQ(error_of([&] { bp::decode(status_wire_with_manifest(limits.max_frames + 1), limits); }),
            ErrorCode::kTooLarge);
  // At the limit the entries are read and matched against the frames received.
  EXPECT_EQ(error_of([&] { bp::decode(status_wire_with_manifest(limits.max_frames), limits); }),
            ErrorCode::kFrameCountMismatch);
}

TEST(WireBounds, ScanIdMustBeAnId) {
  for (const std::string& bad : {std::string(), std::string(129, 'a'), std::string("scan 1"), std::string("scan\n1")}) {
    bp::Message m = bp::decode(bp::encode(bp::make_scan_result_request("r", {"scan-1", {bp::ResultPart::kMetrics}, {}})));
    m.header["scan_id"] = bad;
    EXPECT_EQ(error_of([&] { bp::parse_scan_result_request(m); }), ErrorCode::kInvalidRequest) << bad;
  }
  bp::Message ok = bp::decode(bp::encode(bp::make_scan_result_request("r", {std::string(128, 'a'), {bp::ResultPart::kMetrics}, {}})));
  EXPECT_EQ(bp::parse_scan_result_request(ok).scan_id.size(), 128u);
}

TEST(WireBounds, LabelTableFrameIsBounded) {
  bp::PreopLoadRequest r;
  r.t1 = bp::media::nifti_frame("t1", bp::testing::fake_nifti(4, 4, 4));
  r.labels = bp::media::nifti_frame("labels", bp::testing::fake_nifti(4, 4, 4));
  const std::string table = R"({"v": 1, "structures": {"brain": [1]}})";
  auto padded = [&](std::size_t size) { return table + std::string(size - table.size(), ' '); };
  r.label_table = bp::media::json_frame("label_table", padded(bp::kMaxLabelTableBytes));
  EXPECT_EQ(bp::parse_preop_load_request(bp::decode(bp::encode(bp::make_preop_load_request("p", r)))).label_table->bytes.size(),
            bp::kMaxLabelTableBytes);
  r.label_table = bp::media::json_frame("label_table", padded(bp::kMaxLabelTableBytes + 1));
  EXPECT_EQ(error_of([&] { bp::parse_preop_load_request(bp::decode(bp::encode(bp::make_preop_load_request("p", r)))); }),
            ErrorCode::kInvalidRequest);
  EXPECT_EQ(error_of([&] { bp::parse_label_map_json(padded(bp::kMaxLabelTableBytes + 1)); }), ErrorCode::kInvalidRequest);
}

TEST(WireBounds, ShutdownReasonIsBounded) {
  const auto reason = [](std::size_t n) {
    return bp::decode(bp::encode(bp::make_shutdown_request("s", {std::string(n, 'r')})));
  };
  EXPECT_EQ(bp::parse_shutdown_request(reason(bp::kMaxShutdownReasonLength)).reason.size(), bp::kMaxShutdownReasonLength);
  EXPECT_EQ(error_of([&] { bp::parse_shutdown_request(reason(bp::kMaxShutdownReasonLength + 1)); }),
            ErrorCode::kInvalidRequest);
}

}  // namespace
