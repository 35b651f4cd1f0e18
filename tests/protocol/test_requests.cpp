// Every request and reply survives encode -> decode -> parse unchanged, and
// the typed parsers refuse missing, extra or ill-typed fields and frames.
#include <gtest/gtest.h>

#include <functional>

#include "protocol/fields.h"
#include "protocol/media.h"
#include "protocol/requests.h"
#include "test_util.h"

namespace bp = brainshift::protocol;
using bp::ErrorCode;
using nlohmann::json;

namespace {

// What a peer gets: the message after a trip through the wire format.
bp::Message wire_trip(const bp::Message& m) { return bp::decode(bp::encode(m)); }

using bp::testing::error_of;

bp::Frame labels_frame() { return bp::media::nifti_frame("labels", bp::testing::fake_nifti(5, 4, 3)); }

TEST(ScanList, AFullListingFitsTheClientsHeaderLimit) {
  // kMaxScanListLimit scans with the longest client ids and failure messages
  // like the store's: the reply must be readable by a client.
  bp::ScanListReply r;
  for (std::uint64_t i = 0; i < bp::kMaxScanListLimit; ++i) {
    bp::ScanSummary s;
    s.scan_id = "scan-" + std::to_string(100000 + i);
    s.client_scan_id = std::string(120, 'c') + std::to_string(10000 + i);
    s.state = bp::ScanState::kFailed;
    s.received_at = "2026-11-22T06:55:05.123Z";
    s.finished_at = s.received_at;
    s.error = bp::ErrorInfo{ErrorCode::kInternal, std::string(300, 'm')};
    r.scans.push_back(s);
  }
  const auto wire = bp::encode(bp::make_scan_list_reply("list", r));
  EXPECT_GT(wire[0].size(), bp::Limits{}.max_header_bytes) << "the case this limit exists for";
  const auto decoded = bp::parse_scan_list_reply(bp::decode(wire, bp::Limits::client_inbound()));
  EXPECT_EQ(decoded.scans.size(), bp::kMaxScanListLimit);
}

}  // namespace

TEST(Status, RequestAndReplyRoundTrip) {
  const auto req = wire_trip(bp::make_status_request("s1"));
  EXPECT_NO_THROW(bp::parse_status_request(req));
  EXPECT_EQ(req.request_id(), "s1");

  bp::StatusReply r;
  r.state = bp::ServerState::kLoadingPreop;
  r.progress = bp::Progress{"mesh", 0.4};
  r.versions = {{"brainshift", "0.1.0"}, {"petsc", "3.18.4"}};
  r.preop_id = "p-1";
  r.mpi_ranks = 2;
  r.queue = {1, 8};
  r.last_error = bp::ErrorInfo{ErrorCode::kInvalidRequest, "labels and t1 grids differ"};
  r.openigtlink = bp::OpenIgtlinkInfo{18944, 2, 17, 3};
  const auto back = bp::parse_status_reply(wire_trip(bp::make_status_reply("s1", r)));
  r.versions["protocol"] = "1";  // always added by the builder
  EXPECT_EQ(back, r);

  bp::StatusReply ready;
  ready.state = bp::ServerState::kProcessing;
  ready.mesh = bp::MeshSize{43733, 215037};
  ready.current_scan_id = "s-000003";
  const auto back2 = bp::parse_status_reply(wire_trip(bp::make_status_reply("s2", ready)));
  EXPECT_EQ(back2.mesh, ready.mesh);
  EXPECT_EQ(back2.current_scan_id, ready.current_scan_id);
  EXPECT_FALSE(back2.progress.has_value());
  EXPECT_FALSE(back2.openigtlink.has_value());
}

TEST(Status, RequestWithAFrameIsRefused) {
  auto m = bp::make_status_request("s1");
  m.frames.push_back(labels_frame());
  EXPECT_EQ(error_of([&] { bp::parse_status_request(wire_trip(m)); }), ErrorCode::kInvalidRequest);
}

TEST(Status, ReplyWithBadStateOrFractionIsRefused) {
  auto m = bp::make_status_reply("s1", bp::StatusReply{});
  m.header["state"] = "sleeping";
  EXPECT_EQ(error_of([&] { bp::parse_status_reply(m); }), ErrorCode::kInvalidRequest);
  m = bp::make_status_reply("s1", bp::StatusReply{.progress = bp::Progress{"mesh", 0.5}});
  m.header["progress"]["fraction"] = 1.5;
  EXPECT_EQ(error_of([&] { bp::parse_status_reply(m); }), ErrorCode::kInvalidRequest);
  m = bp::make_status_reply("s1", bp::StatusReply{.openigtlink = bp::OpenIgtlinkInfo{18944, 1, 9, 0}});
  m.header["openigtlink"]["messages_dropped"] = -1;
  EXPECT_EQ(error_of([&] { bp::parse_status_reply(m); }), ErrorCode::kInvalidRequest);
  m.header["openigtlink"].erase("messages_dropped");
  EXPECT_EQ(error_of([&] { bp::parse_status_reply(m); }), ErrorCode::kInvalidRequest);
}

TEST(PreopLoad, DefaultAtlasRoundTrip) {
  const auto back = bp::parse_preop_load_request(
      wire_trip(bp::make_preop_load_request("p", {.use_default_atlas = true})));
  EXPECT_TRUE(back.use_default_atlas);
  EXPECT_FALSE(back.t1.has_value());
}

TEST(PreopLoad, FramesRoundTripWithLabelTable) {
  bp::LabelMap table;
  table.structures["brain"] = {1};
  table.structures["corticospinal_tract"] = {7, 8};
  table.structures["arcuate_fasciculus"] = {9};  // any name of the daemon's table
  bp::PreopLoadRequest r;
  r.t1 = bp::media::nifti_frame("t1", bp::testing::fake_gzip(4096));
  r.labels = bp::media::nifti_frame("labels", bp::testing::fake_nifti(8, 8, 8));
  r.label_table = bp::media::json_frame("label_table", bp::make_label_map_json(table));
  const auto back = bp::parse_preop_load_request(wire_trip(bp::make_preop_load_request("p", r)));
  EXPECT_FALSE(back.use_default_atlas);
  ASSERT_TRUE(back.t1 && back.labels && back.label_table);
  EXPECT_EQ(back.t1->bytes, r.t1->bytes);
  EXPECT_EQ(back.labels->bytes, r.labels->bytes);
  EXPECT_EQ(bp::parse_label_map_json(back.label_table->bytes), table);

  const auto reply = bp::parse_preop_load_reply(wire_trip(bp::make_preop_load_reply("p", {"p-7"})));
  EXPECT_EQ(reply.preop_id, "p-7");
}

TEST(PreopLoad, RefusesMissingFramesFramesWithDefaultAtlasAndBadContent) {
  bp::PreopLoadRequest only_t1;
  only_t1.t1 = bp::media::nifti_frame("t1", bp::testing::fake_nifti(2, 2, 2));
  EXPECT_EQ(error_of([&] { bp::parse_preop_load_request(wire_trip(bp::make_preop_load_request("p", only_t1))); }),
            ErrorCode::kInvalidRequest);

  bp::PreopLoadRequest both = only_t1;
  both.use_default_atlas = true;
  EXPECT_EQ(error_of([&] { bp::parse_preop_load_request(wire_trip(bp::make_preop_load_request("p", both))); }),
            ErrorCode::kInvalidRequest);

  bp::PreopLoadRequest not_nifti = only_t1;
  not_nifti.labels = bp::Frame{"labels", std::string(bp::media::kNifti), "this is a PNG"};
  EXPECT_EQ(error_of([&] { bp::parse_preop_load_request(wire_trip(bp::make_preop_load_request("p", not_nifti))); }),
            ErrorCode::kInvalidRequest);

  bp::PreopLoadRequest bad_table = only_t1;
  bad_table.labels = bp::media::nifti_frame("labels", bp::testing::fake_nifti(2, 2, 2));
  bad_table.label_table = bp::media::json_frame("label_table", R"({"v":1,"structures":{"../ventricles":[2]}})");
  EXPECT_EQ(error_of([&] { bp::parse_preop_load_request(wire_trip(bp::make_preop_load_request("p", bad_table))); }),
            ErrorCode::kInvalidRequest);
}

// Structure names are the daemon's label table's (it checks them); the codec
// refuses what cannot be one: a name that would not be a safe file name.
TEST(LabelTable, RefusesBadStructureNamesAndOutOfRangeValues) {
  EXPECT_EQ(bp::parse_label_map_json(R"({"v":1,"structures":{"brain":[1],"arcuate_fasciculus":[9]}})")
                .structures.at("arcuate_fasciculus"),
            std::vector<std::uint16_t>{9});
  for (const char* name : {"../x", "Liver", "", "5th", "model.brain"})
    EXPECT_THROW(bp::parse_label_map_json(R"({"v":1,"structures":{")" + std::string(name) + R"(":[9]}})"),
                 bp::ProtocolError) << name;
  EXPECT_THROW(bp::parse_label_map_json(R"({"v":1,"structures":{}})"), bp::ProtocolError);
  json many = {{"v", 1}, {"structures", json::object()}};
  for (std::size_t i = 0; i <= bp::kMaxStructures; ++i) many["structures"]["s" + std::to_string(i)] = {i + 1};
  EXPECT_THROW(bp::parse_label_map_json(many.dump()), bp::ProtocolError);
  EXPECT_THROW(bp::parse_label_map_json(R"({"v":1,"structures":{"brain":[70000]}})"),
               bp::ProtocolError);
  EXPECT_THROW(bp::parse_label_map_json(R"({"v":1,"structures":{"brain":[0]}})"),
               bp::ProtocolError);
  EXPECT_THROW(bp::parse_label_map_json("not json"), bp::ProtocolError);
}

TEST(ScanPush, RoundTripWithImageAndClientScanId) {
  bp::ScanPushRequest r{labels_frame(), bp::media::nifti_frame("image", bp::testing::fake_gzip(2048)),
                        "or1-scan-0042"};
  const auto back = bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", r)));
  ASSERT_TRUE(back.labels.has_value());
  EXPECT_EQ(back.labels->bytes, r.labels->bytes);
  ASSERT_TRUE(back.image.has_value());
  EXPECT_EQ(back.image->bytes, r.image->bytes);
  EXPECT_EQ(back.image->media_type, bp::media::kNiftiGz);
  EXPECT_EQ(back.client_scan_id, r.client_scan_id);

  const auto reply = bp::parse_scan_push_reply(wire_trip(bp::make_scan_push_reply("q", {"s-000001", true})));
  EXPECT_EQ(reply, (bp::ScanPushReply{"s-000001", true}));
}

TEST(ScanPush, LabelsOnlyIsEnough) {
  const auto back = bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", {labels_frame()})));
  EXPECT_FALSE(back.image.has_value());
  EXPECT_FALSE(back.client_scan_id.has_value());
}

// Revision 4: an image alone is a scan (the daemon segments it).
TEST(ScanPush, ImageAloneIsEnough) {
  bp::ScanPushRequest r;
  r.image = bp::media::nifti_frame("image", bp::testing::fake_gzip(2048));
  const auto m = wire_trip(bp::make_scan_push_request("q", r));
  ASSERT_EQ(m.frames.size(), 1u);
  const auto back = bp::parse_scan_push_request(m);
  EXPECT_FALSE(back.labels.has_value());
  ASSERT_TRUE(back.image.has_value());
  EXPECT_EQ(back.image->bytes, r.image->bytes);
}

// Revision 5: labels with their image may say how they are used.
TEST(ScanPush, LabelsUseTravelsWithBothFramesAndIsCheckedOtherwise) {
  bp::ScanPushRequest r{labels_frame(), bp::media::nifti_frame("image", bp::testing::fake_gzip(2048))};
  r.labels_use = "exact";
  EXPECT_EQ(bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", r))).labels_use,
            std::optional<std::string>("exact"));
  EXPECT_FALSE(bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", {labels_frame()})))
                   .labels_use.has_value());
  r.labels_use = "mostly";
  EXPECT_EQ(error_of([&] { bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", r))); }),
            ErrorCode::kInvalidRequest);
  bp::ScanPushRequest alone{labels_frame()};
  alone.labels_use = "refine";  // nothing to refine them by
  try {
    bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", alone)));
    FAIL();
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidRequest);
    EXPECT_NE(std::string(e.what()).find("labels_use"), std::string::npos) << e.what();
  }
}

TEST(ScanPush, RefusesNoFramesExtraFramesAndBadIds) {
  try {
    bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", {})));
    FAIL();
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidRequest);
    // The message names both frames a scan may have.
    EXPECT_NE(std::string(e.what()).find("\"labels\""), std::string::npos);
    EXPECT_NE(std::string(e.what()).find("\"image\""), std::string::npos);
  }

  auto extra = bp::make_scan_push_request("q", {labels_frame()});
  extra.frames.push_back(bp::media::json_frame("notes", "{}"));
  try {
    bp::parse_scan_push_request(wire_trip(extra));
    FAIL();
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidRequest);
    EXPECT_EQ(e.request_id().value_or(""), "q");  // the server can still answer it
    EXPECT_NE(std::string(e.what()).find("notes"), std::string::npos);
  }

  auto bad_id = bp::make_scan_push_request("q", {labels_frame()});
  bad_id.header["client_scan_id"] = "two words";
  EXPECT_EQ(error_of([&] { bp::parse_scan_push_request(wire_trip(bad_id)); }), ErrorCode::kInvalidRequest);

  auto wrong_media = bp::make_scan_push_request("q", {labels_frame()});
  wrong_media.frames[0].media_type = std::string(bp::media::kVtp);
  EXPECT_EQ(error_of([&] { bp::parse_scan_push_request(wire_trip(wrong_media)); }), ErrorCode::kInvalidRequest);
}

// PROTOCOL.md "Patient identity": DICOM's PatientID, carried by preop.load
// and scan.push, compared without DICOM's padding spaces.
TEST(PatientId, TravelsWithPreopLoadAndScanPushAndIsChecked) {
  bp::ScanPushRequest push;
  push.labels = labels_frame();
  push.patient_id = "  MRN 0042 ";
  EXPECT_EQ(bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", push))).patient_id.value_or(""),
            "MRN 0042");
  bp::PreopLoadRequest preop;
  preop.t1 = bp::media::nifti_frame("t1", bp::testing::fake_nifti(2, 2, 2));
  preop.labels = bp::media::nifti_frame("labels", bp::testing::fake_nifti(2, 2, 2));
  preop.patient_id = "MRN 0042";
  EXPECT_EQ(bp::parse_preop_load_request(wire_trip(bp::make_preop_load_request("p", preop))).patient_id.value_or(""),
            "MRN 0042");
  push.patient_id.reset();
  EXPECT_FALSE(bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", push))).patient_id);

  push.patient_id = "M\xC3\x9CLLER-7";  // UTF-8 is text
  EXPECT_EQ(bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", push))).patient_id.value_or(""),
            "M\xC3\x9CLLER-7");
  EXPECT_FALSE(bp::detail::normalised_patient_id("M\xDCLLER-7"));  // Latin-1 bytes are not
  for (const std::string& bad : {std::string(""), std::string("   "), std::string(65, 'x'), std::string("a\nb"),
                                std::string("tab\there")}) {
    push.patient_id = bad;
    EXPECT_EQ(error_of([&] { bp::parse_scan_push_request(wire_trip(bp::make_scan_push_request("q", push))); }),
              ErrorCode::kInvalidRequest)
        << "\"" << bad << "\"";
  }
  auto not_text = bp::make_scan_push_request("q", {labels_frame()});
  not_text.header["patient_id"] = 42;
  EXPECT_EQ(error_of([&] { bp::parse_scan_push_request(wire_trip(not_text)); }), ErrorCode::kInvalidRequest);
  // The default atlas is no patient's.
  EXPECT_EQ(error_of([&] {
              bp::parse_preop_load_request(
                  wire_trip(bp::make_preop_load_request("p", {.use_default_atlas = true, .patient_id = "MRN 0042"})));
            }),
            ErrorCode::kInvalidRequest);

  bp::StatusReply status;
  status.preop_id = "p-1";
  status.preop_patient_id = "MRN 0042";
  EXPECT_EQ(bp::parse_status_reply(wire_trip(bp::make_status_reply("s", status))).preop_patient_id.value_or(""),
            "MRN 0042");
}

TEST(ScanResult, RequestRoundTrip) {
  bp::ScanResultRequest r{"s-000001",
                          {bp::ResultPart::kDisplacement, bp::ResultPart::kModels, bp::ResultPart::kTimings},
                          {"brain", "tumor"}};
  EXPECT_EQ(bp::parse_scan_result_request(wire_trip(bp::make_scan_result_request("r", r))), r);
}

TEST(ScanResult, RequestRefusesEmptyRepeatedOrUnknownParts) {
  auto m = bp::make_scan_result_request("r", {"s-1", {bp::ResultPart::kMetrics}, {}});
  m.header["parts"] = json::array();
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_request(m); }), ErrorCode::kInvalidRequest);
  m.header["parts"] = {"metrics", "metrics"};
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_request(m); }), ErrorCode::kInvalidRequest);
  m.header["parts"] = {"jacobian"};
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_request(m); }), ErrorCode::kInvalidRequest);
  m.header["parts"] = {"models"};
  m.header["structures"] = {"../brain"};
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_request(m); }), ErrorCode::kInvalidRequest);
  m.header["structures"] = json::array();
  for (std::size_t i = 0; i <= bp::kMaxStructures; ++i) m.header["structures"].push_back("s" + std::to_string(i));
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_request(m); }), ErrorCode::kInvalidRequest);
  m.header.erase("structures");
  m.header["parts"] = {"metrics"};
  m.header.erase("scan_id");
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_request(m); }), ErrorCode::kInvalidRequest);
}

TEST(ScanResult, ReplyRoundTripWithEveryKindOfFrame) {
  bp::ScanResultReply r;
  r.scan_id = "s-000001";
  r.frames = {bp::media::nifti_frame(bp::frame_name(bp::ResultPart::kDisplacement), bp::testing::fake_gzip(999)),
              {bp::frame_name(bp::ResultPart::kDisplacementItk), std::string(bp::media::kItkH5), bp::testing::fake_h5()},
              bp::media::nifti_frame("warped_labels", bp::testing::fake_nifti(3, 3, 3)),
              {bp::model_frame_name("ventricles"), std::string(bp::media::kVtp), bp::testing::fake_vtp()},
              bp::media::json_frame("metrics", R"({"surface_rms_mm": 0.8})"),
              {bp::frame_name(bp::ResultPart::kReport), std::string(bp::media::kPng),
               std::string("\x89PNG\r\n\x1a\n....", 12)}};
  r.unavailable = {{"warped_image", "no intraop image was pushed"}, {"model.tumor", "no tumor label"},
                   {"report", "being rendered", true}};
  r.result = bp::ResultKindInfo{bp::ResultKind::affine_only_fallback, "surface match diverged"};
  const auto back = bp::parse_scan_result_reply(wire_trip(bp::make_scan_result_reply("r", r)));
  EXPECT_EQ(back.scan_id, r.scan_id);
  EXPECT_EQ(back.result, r.result);
  ASSERT_EQ(back.frames.size(), r.frames.size());
  for (std::size_t i = 0; i < r.frames.size(); ++i) {
    EXPECT_EQ(back.frames[i].name, r.frames[i].name);
    EXPECT_EQ(back.frames[i].bytes, r.frames[i].bytes);
  }
  EXPECT_EQ(back.unavailable, r.unavailable);
  EXPECT_NE(back.find("model.ventricles"), nullptr);
}

TEST(ScanResult, ReportIsAPartAndPendingIsOptionalOnTheWire) {
  EXPECT_EQ(bp::result_part_from_string("report"), bp::ResultPart::kReport);
  EXPECT_EQ(bp::frame_name(bp::ResultPart::kReport), "report");
  bp::ScanResultReply r;
  r.scan_id = "s-1";
  r.unavailable = {{"report", "later", true}, {"warped_image", "never"}};
  const auto m = bp::make_scan_result_reply("r", r);
  EXPECT_TRUE(m.header["unavailable"][0].at("pending").get<bool>());
  EXPECT_FALSE(m.header["unavailable"][1].contains("pending"));  // absent = false (older peers)
  // A report frame must be a PNG.
  r.frames = {{"report", std::string(bp::media::kPng), "GIF89a"}};
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_reply(wire_trip(bp::make_scan_result_reply("r", r))); }),
            ErrorCode::kInvalidRequest);
  r.frames = {bp::media::json_frame("report", "{}")};
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_reply(wire_trip(bp::make_scan_result_reply("r", r))); }),
            ErrorCode::kInvalidRequest);
}

TEST(ScanResult, ReplyRefusesAFrameWithTheWrongMediaType) {
  bp::ScanResultReply r;
  r.scan_id = "s-1";
  r.frames = {bp::media::json_frame("displacement", "{}")};
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_reply(wire_trip(bp::make_scan_result_reply("r", r))); }),
            ErrorCode::kInvalidRequest);
  // Right media type, wrong bytes: a server bug the client must not pass on.
  r.frames = {{"model.brain", std::string(bp::media::kVtp), "solid ascii STL"}};
  EXPECT_EQ(error_of([&] { bp::parse_scan_result_reply(wire_trip(bp::make_scan_result_reply("r", r))); }),
            ErrorCode::kInvalidRequest);
}

TEST(ScanList, RoundTrip) {
  EXPECT_EQ(bp::parse_scan_list_request(wire_trip(bp::make_scan_list_request("l", {25}))).limit, 25u);
  EXPECT_EQ(bp::parse_scan_list_request(wire_trip(bp::make_scan_list_request("l"))).limit, 100u);
  auto too_many = bp::make_scan_list_request("l", {5});
  too_many.header["limit"] = bp::kMaxScanListLimit + 1;
  EXPECT_EQ(error_of([&] { bp::parse_scan_list_request(too_many); }), ErrorCode::kInvalidRequest);

  bp::ScanListReply r;
  r.scans.push_back({"s-2", "c-2", bp::ScanState::kProcessing, "2024-05-01T10:00:00.000Z", std::nullopt,
                     "solve", std::nullopt});
  r.scans.push_back({"s-1", std::nullopt, bp::ScanState::kFailed, "2024-05-01T09:00:00.000Z",
                     "2024-05-01T09:00:05.250Z", std::nullopt,
                     bp::ErrorInfo{ErrorCode::kInvalidRequest, "labels have no brain voxels"}});
  r.scans.push_back({"s-0", std::nullopt, bp::ScanState::kDone, "2024-05-01T08:00:00.000Z",
                     "2024-05-01T08:00:02.000Z", std::nullopt, std::nullopt,
                     bp::ResultKindInfo{bp::ResultKind::affine_only_fallback, "field folds"}});
  EXPECT_EQ(bp::parse_scan_list_reply(wire_trip(bp::make_scan_list_reply("l", r))), r);
  auto unknown_kind = bp::make_scan_list_reply("l", r);
  unknown_kind.header["scans"][2]["kind"] = "elastic";
  EXPECT_EQ(error_of([&] { bp::parse_scan_list_reply(unknown_kind); }), ErrorCode::kInvalidRequest);
}

bp::LabelsReply shipped_like_labels() {
  bp::LabelsReply r;
  r.labels.push_back({1, "cerebrum", "cerebrum", "parenchyma", {40, 220, 60}, true});
  r.labels.push_back({2, "ventricles", "ventricles", "cavity", {0, 200, 255}, true});
  r.labels.push_back({5, "arcuate_fasciculus", "af", "structure", {255, 140, 0}, false});
  return r;
}

TEST(LabelsGet, RequestAndReplyRoundTrip) {
  const bp::Message request = wire_trip(bp::make_labels_request("l1"));
  EXPECT_EQ(request.type(), bp::MessageType::kLabelsGet);
  EXPECT_EQ(bp::kind_of(request.type()), bp::MessageKind::kRequest);
  EXPECT_EQ(bp::reply_type_for(request.type()), bp::MessageType::kLabelsGetReply);
  EXPECT_NO_THROW(bp::parse_labels_request(request));
  const bp::Message reply = wire_trip(bp::make_labels_reply("l1", shipped_like_labels()));
  EXPECT_EQ(reply.header["labels"][0]["colour"], "#28dc3c");
  EXPECT_EQ(bp::parse_labels_reply(reply), shipped_like_labels());
}

TEST(LabelsGet, ColoursAreHashAndSixHexDigits) {
  EXPECT_EQ(bp::colour_to_hex({255, 140, 0}), "#ff8c00");
  EXPECT_EQ(bp::colour_from_hex("#FF8c00"), (bp::Rgb{255, 140, 0}));
  for (const char* bad : {"", "ff8c00", "#ff8c0", "#ff8c000", "#gg8c00", "#ff c00"})
    EXPECT_FALSE(bp::colour_from_hex(bad)) << bad;
}

TEST(LabelsGet, RefusesAFrameAndABadTable) {
  bp::Message with_frame = bp::make_labels_request("l");
  with_frame.frames.push_back(bp::media::json_frame("labels", "{}"));
  EXPECT_EQ(error_of([&] { bp::parse_labels_request(with_frame); }), ErrorCode::kInvalidRequest);

  auto refused = [&](const std::function<void(json&)>& spoil) {
    bp::Message m = bp::make_labels_reply("l", shipped_like_labels());
    spoil(m.header["labels"]);
    return error_of([&] { bp::parse_labels_reply(wire_trip(m)); }) == ErrorCode::kInvalidRequest;
  };
  EXPECT_TRUE(refused([](json& l) { l = json::array(); }));                      // no label
  EXPECT_TRUE(refused([](json& l) { l = json::object(); }));                     // not an array
  EXPECT_TRUE(refused([](json& l) { l[1]["value"] = 0; }));                      // background
  EXPECT_TRUE(refused([](json& l) { l[1]["value"] = 65536; }));                  // beyond uint16
  EXPECT_TRUE(refused([](json& l) { l[1]["value"] = "2"; }));                    // not a number
  EXPECT_TRUE(refused([](json& l) { l[1]["value"] = 1; }));                      // a value twice
  EXPECT_TRUE(refused([](json& l) { l[1]["name"] = "cerebrum"; }));              // a name twice
  EXPECT_TRUE(refused([](json& l) { l[1]["name"] = "../etc"; }));                // not a structure name
  EXPECT_TRUE(refused([](json& l) { l[2].erase("name"); }));                     // missing name
  EXPECT_TRUE(refused([](json& l) { l[2]["short_name"] = "arcuate_fasc"; }));    // 12 characters
  EXPECT_TRUE(refused([](json& l) { l[2]["role"] = "organ"; }));                 // unknown role
  EXPECT_TRUE(refused([](json& l) { l[1]["role"] = "parenchyma"; }));            // two parenchymas
  EXPECT_TRUE(refused([](json& l) { l[0]["role"] = "structure"; }));             // none
  EXPECT_TRUE(refused([](json& l) { l[0]["colour"] = "green"; }));               // not #rrggbb
  EXPECT_TRUE(refused([](json& l) { l[0]["model"] = "yes"; }));                  // not a boolean
  EXPECT_TRUE(refused([&](json& l) {                                             // over 64 labels
    for (int v = 10; v < 10 + static_cast<int>(bp::kMaxStructures); ++v)
      l.push_back({{"value", v}, {"name", "s" + std::to_string(v)}, {"short_name", "s" + std::to_string(v)},
                   {"role", "structure"}, {"colour", "#000000"}});
  }));
  // "model" may be absent (default true); nothing else was spoiled above.
  bp::Message no_model = bp::make_labels_reply("l", shipped_like_labels());
  no_model.header["labels"][2].erase("model");
  EXPECT_TRUE(bp::parse_labels_reply(wire_trip(no_model)).labels[2].model);
}

TEST(Shutdown, RoundTrip) {
  EXPECT_EQ(bp::parse_shutdown_request(wire_trip(bp::make_shutdown_request("x", {"end of case"}))).reason,
            "end of case");
  EXPECT_EQ(bp::parse_shutdown_request(wire_trip(bp::make_shutdown_request("x"))).reason, "");
  EXPECT_NO_THROW(bp::parse_shutdown_reply(wire_trip(bp::make_shutdown_reply("x"))));
}

TEST(ErrorReply, RoundTripAndThrowIfError) {
  const auto m = wire_trip(bp::make_error_reply("q9", ErrorCode::kBusy, "queue full (8 scans)"));
  EXPECT_EQ(m.request_id(), "q9");
  const auto info = bp::parse_error_reply(m);
  EXPECT_EQ(info.code, ErrorCode::kBusy);
  EXPECT_EQ(info.message, "queue full (8 scans)");
  try {
    bp::throw_if_error(m);
    FAIL();
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kBusy);
    EXPECT_EQ(e.request_id().value_or(""), "q9");
  }
  EXPECT_NO_THROW(bp::throw_if_error(bp::make_status_request("ok")));
}

TEST(ErrorReply, EmptyMessageIsAllowed) {
  const auto m = wire_trip(bp::make_error_reply("q", ErrorCode::kInternal, ""));
  EXPECT_EQ(bp::parse_error_reply(m), (bp::ErrorInfo{ErrorCode::kInternal, ""}));
}

TEST(ErrorReply, TypedParsersRethrowAnErrorReply) {
  const auto m = wire_trip(bp::make_error_reply("q", ErrorCode::kNotReady, "no preop loaded"));
  EXPECT_EQ(error_of([&] { bp::parse_scan_push_reply(m); }), ErrorCode::kNotReady);
}

TEST(ErrorReply, BuiltFromADecodeFailureEchoesTheRequestId) {
  try {
    bp::decode({json{{"v", 2}, {"type", "status"}, {"request_id", "old-client-1"}}.dump()});
    FAIL();
  } catch (const bp::ProtocolError& e) {
    const auto reply = wire_trip(bp::make_error_reply(e));
    EXPECT_EQ(reply.request_id(), "old-client-1");
    EXPECT_EQ(bp::parse_error_reply(reply).code, ErrorCode::kVersionMismatch);
  }
  try {
    bp::decode({"not json"});
    FAIL();
  } catch (const bp::ProtocolError& e) {
    const auto reply = wire_trip(bp::make_error_reply(e));
    EXPECT_EQ(reply.request_id(), "");
    EXPECT_EQ(bp::parse_error_reply(reply).code, ErrorCode::kMalformedJson);
  }
}

TEST(TypedParsers, RefuseAMessageOfAnotherType) {
  const auto m = wire_trip(bp::make_status_request("s"));
  EXPECT_EQ(error_of([&] { bp::parse_scan_push_request(m); }), ErrorCode::kInvalidRequest);
}
