// The codec: encode/decode round trip and every envelope-level refusal.
#include <gtest/gtest.h>

#include "protocol/media.h"
#include "protocol/message.h"
#include "protocol/version.h"
#include "test_util.h"

namespace bp = brainshift::protocol;
using bp::ErrorCode;
using nlohmann::json;

namespace {

bp::Message push_with_two_frames() {
  bp::Message m = bp::make_message(bp::MessageType::kScanPush, "req-1");
  m.frames.push_back(bp::media::nifti_frame("labels", bp::testing::fake_nifti(4, 3, 2)));
  m.frames.push_back(bp::media::nifti_frame("image", bp::testing::fake_gzip(100)));
  return m;
}

// Runs decode and returns the code it threw; fails the test if it did not throw.
ErrorCode decode_error(std::vector<std::string> wire, const bp::Limits& limits = {}) {
  try {
    bp::decode(std::move(wire), limits);
  } catch (const bp::ProtocolError& e) {
    return e.code();
  }
  ADD_FAILURE() << "decode accepted a message it should refuse";
  return ErrorCode::kInternal;
}

std::vector<std::string> with_header(std::vector<std::string> wire, const json& header) {
  wire[0] = header.dump();
  return wire;
}

}  // namespace

TEST(Codec, RoundTripKeepsHeaderFramesAndBinaryBytes) {
  const bp::Message m = push_with_two_frames();
  const auto wire = bp::encode(m);
  ASSERT_EQ(wire.size(), 3u);
  const json header = json::parse(wire[0]);
  EXPECT_EQ(header["v"], bp::kProtocolVersion);
  EXPECT_EQ(header["type"], "scan.push");
  EXPECT_EQ(header["frames"][0]["name"], "labels");
  EXPECT_EQ(header["frames"][0]["media_type"], std::string(bp::media::kNifti));
  EXPECT_EQ(header["frames"][0]["size"], 352u + 24u);
  EXPECT_EQ(header["frames"][1]["media_type"], std::string(bp::media::kNiftiGz));

  const bp::Message back = bp::decode(wire);
  EXPECT_EQ(back.type(), bp::MessageType::kScanPush);
  EXPECT_EQ(back.request_id(), "req-1");
  ASSERT_EQ(back.frames.size(), 2u);
  EXPECT_EQ(back.frames[0].bytes, m.frames[0].bytes);  // NUL bytes survive
  EXPECT_EQ(back.frames[1].bytes, m.frames[1].bytes);
  EXPECT_EQ(back.find_frame("image")->media_type, bp::media::kNiftiGz);
  EXPECT_EQ(back.find_frame("missing"), nullptr);
}

TEST(Codec, EncodeReplacesAStaleManifest) {
  bp::Message m = push_with_two_frames();
  m.header["frames"] = json::array({{{"name", "bogus"}, {"media_type", "x"}, {"size", 1}}});
  EXPECT_EQ(bp::decode(bp::encode(m)).frames.size(), 2u);
}

TEST(Codec, EncodeRefusesWhatDecodeWouldRefuse) {
  bp::Message dup = push_with_two_frames();
  dup.frames[1].name = "labels";
  EXPECT_THROW(bp::encode(dup), bp::ProtocolError);
  bp::Message no_id = bp::make_message(bp::MessageType::kStatus, "");
  EXPECT_THROW(bp::encode(no_id), bp::ProtocolError);
  bp::Message bad_name = push_with_two_frames();
  bad_name.frames[0].name = "Labels With Spaces";
  EXPECT_THROW(bp::encode(bad_name), bp::ProtocolError);
}

TEST(Codec, MalformedJson) {
  EXPECT_EQ(decode_error({"{\"v\":1,"}), ErrorCode::kMalformedJson);
  EXPECT_EQ(decode_error({"[1,2,3]"}), ErrorCode::kMalformedJson);
  EXPECT_EQ(decode_error({std::string("\xff\xfe", 2)}), ErrorCode::kMalformedJson);
  // Inside a string too: an error message quoting it must stay encodable JSON.
  EXPECT_EQ(decode_error({"{\"v\":1,\"type\":\"st\xffus\",\"request_id\":\"r\"}"}), ErrorCode::kMalformedJson);
  EXPECT_EQ(decode_error({R"({"v":1,"type":"\ud800","request_id":"r"})"}), ErrorCode::kMalformedJson);
}

TEST(Codec, EmptyMessageIsABadHeader) { EXPECT_EQ(decode_error({}), ErrorCode::kBadHeader); }

TEST(Codec, MissingOrWrongVersionIsAVersionMismatch) {
  const auto wire = bp::encode(bp::make_message(bp::MessageType::kStatus, "r"));
  json h = json::parse(wire[0]);
  h.erase("v");
  EXPECT_EQ(decode_error(with_header(wire, h)), ErrorCode::kVersionMismatch);
  h["v"] = bp::kProtocolVersion + 1;
  EXPECT_EQ(decode_error(with_header(wire, h)), ErrorCode::kVersionMismatch);
  h["v"] = "1";
  EXPECT_EQ(decode_error(with_header(wire, h)), ErrorCode::kVersionMismatch);
}

TEST(Codec, VersionMismatchStillCarriesTheRequestIdAndSaysWhichVersion) {
  json h{{"v", 7}, {"type", "status"}, {"request_id", "abc"}};
  try {
    bp::decode({h.dump()});
    FAIL() << "accepted version 7";
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kVersionMismatch);
    ASSERT_TRUE(e.request_id().has_value());
    EXPECT_EQ(*e.request_id(), "abc");
    EXPECT_NE(std::string(e.what()).find('7'), std::string::npos);
  }
}

TEST(Codec, UnknownType) {
  json h{{"v", 1}, {"type", "scan.delete"}, {"request_id", "r"}};
  EXPECT_EQ(decode_error({h.dump()}), ErrorCode::kUnknownType);
  h["type"] = 5;
  EXPECT_EQ(decode_error({h.dump()}), ErrorCode::kBadHeader);
}

TEST(Codec, RequestIdMustBePresentBoundedAndPrintable) {
  json h{{"v", 1}, {"type", "status"}};
  EXPECT_EQ(decode_error({h.dump()}), ErrorCode::kBadHeader);
  h["request_id"] = "";
  EXPECT_EQ(decode_error({h.dump()}), ErrorCode::kBadHeader);
  h["request_id"] = 42;
  EXPECT_EQ(decode_error({h.dump()}), ErrorCode::kBadHeader);
  h["request_id"] = std::string(129, 'a');
  EXPECT_EQ(decode_error({h.dump()}), ErrorCode::kBadHeader);
  h["request_id"] = "has space";
  EXPECT_EQ(decode_error({h.dump()}), ErrorCode::kBadHeader);
  h["request_id"] = std::string(128, 'a');
  EXPECT_NO_THROW(bp::decode({h.dump()}));
}

TEST(Codec, EventsAndErrorRepliesMayOmitTheRequestId) {
  EXPECT_NO_THROW(bp::decode({json{{"v", 1}, {"type", "event.scan.done"}}.dump()}));
  EXPECT_NO_THROW(bp::decode({json{{"v", 1}, {"type", "error"}, {"request_id", ""}}.dump()}));
}

TEST(Codec, FewerOrMoreFramesThanDeclared) {
  auto wire = bp::encode(push_with_two_frames());
  auto fewer = wire;
  fewer.pop_back();
  EXPECT_EQ(decode_error(fewer), ErrorCode::kFrameCountMismatch);
  auto more = wire;
  more.push_back("extra");
  EXPECT_EQ(decode_error(more), ErrorCode::kFrameCountMismatch);
  json h = json::parse(wire[0]);
  h.erase("frames");  // no manifest but frames sent
  EXPECT_EQ(decode_error(with_header(wire, h)), ErrorCode::kFrameCountMismatch);
}

TEST(Codec, DeclaredSizeMustMatchReceivedSize) {
  auto wire = bp::encode(push_with_two_frames());
  json h = json::parse(wire[0]);
  h["frames"][1]["size"] = wire[2].size() + 1000;  // claims more than was sent
  try {
    bp::decode(with_header(wire, h));
    FAIL();
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kFrameSizeMismatch);
    EXPECT_EQ(e.request_id().value_or(""), "req-1");
    EXPECT_NE(std::string(e.what()).find("image"), std::string::npos);
  }
  auto truncated = wire;
  truncated[1].resize(10);
  EXPECT_EQ(decode_error(truncated), ErrorCode::kFrameSizeMismatch);
}

TEST(Codec, BadManifestEntries) {
  auto wire = bp::encode(push_with_two_frames());
  json h = json::parse(wire[0]);
  json bad = h;
  bad["frames"][0]["size"] = -1;
  EXPECT_EQ(decode_error(with_header(wire, bad)), ErrorCode::kBadHeader);
  bad = h;
  bad["frames"][1]["name"] = "labels";
  EXPECT_EQ(decode_error(with_header(wire, bad)), ErrorCode::kBadHeader);
  bad = h;
  bad["frames"][0].erase("media_type");
  EXPECT_EQ(decode_error(with_header(wire, bad)), ErrorCode::kBadHeader);
  bad = h;
  bad["frames"] = "labels";
  EXPECT_EQ(decode_error(with_header(wire, bad)), ErrorCode::kBadHeader);
}

TEST(Codec, SizeLimits) {
  const auto wire = bp::encode(push_with_two_frames());
  bp::Limits frame_limit;
  frame_limit.max_frame_bytes = 200;  // labels frame is 376 bytes
  EXPECT_EQ(decode_error(wire, frame_limit), ErrorCode::kTooLarge);
  bp::Limits total_limit;
  total_limit.max_total_bytes = 400;  // 376 + 100
  EXPECT_EQ(decode_error(wire, total_limit), ErrorCode::kTooLarge);
  bp::Limits header_limit;
  header_limit.max_header_bytes = 50;
  EXPECT_EQ(decode_error(wire, header_limit), ErrorCode::kTooLarge);
  bp::Limits count_limit;
  count_limit.max_frames = 1;
  EXPECT_EQ(decode_error(wire, count_limit), ErrorCode::kTooLarge);
  bp::Limits exact;
  exact.max_frame_bytes = 376;
  exact.max_total_bytes = 476;
  EXPECT_NO_THROW(bp::decode(wire, exact));
}

TEST(Codec, TooLargeStillCarriesTheRequestId) {
  bp::Limits tiny;
  tiny.max_frame_bytes = 10;
  try {
    bp::decode(bp::encode(push_with_two_frames()), tiny);
    FAIL();
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kTooLarge);
    EXPECT_EQ(e.request_id().value_or(""), "req-1");
  }
}

TEST(MessageTypes, EveryNameRoundTripsAndKindsAreRight) {
  for (int i = 0; i <= static_cast<int>(bp::MessageType::kEventServerShutdown); ++i) {
    const auto t = static_cast<bp::MessageType>(i);
    EXPECT_EQ(bp::message_type_from_string(bp::to_string(t)), t);
  }
  EXPECT_EQ(bp::kind_of(bp::MessageType::kShutdown), bp::MessageKind::kRequest);
  EXPECT_EQ(bp::kind_of(bp::MessageType::kError), bp::MessageKind::kReply);
  EXPECT_EQ(bp::kind_of(bp::MessageType::kEventStage), bp::MessageKind::kEvent);
  EXPECT_EQ(bp::reply_type_for(bp::MessageType::kScanPush), bp::MessageType::kScanPushReply);
  EXPECT_THROW(bp::reply_type_for(bp::MessageType::kError), std::invalid_argument);
  EXPECT_FALSE(bp::message_type_from_string("Status").has_value());
}

TEST(ErrorCodes, EveryNameRoundTrips) {
  for (int i = 0; i <= static_cast<int>(ErrorCode::kInternal); ++i) {
    const auto c = static_cast<ErrorCode>(i);
    EXPECT_EQ(bp::error_code_from_string(bp::to_string(c)), c);
  }
  EXPECT_EQ(bp::to_string(ErrorCode::kVersionMismatch), "version_mismatch");
  EXPECT_TRUE(bp::is_retryable(ErrorCode::kBusy));
  EXPECT_FALSE(bp::is_retryable(ErrorCode::kUnauthorised));
}

TEST(Codec, DecodeRequestRefusesRepliesAndEvents) {
  EXPECT_NO_THROW(bp::decode_request(bp::encode(bp::make_message(bp::MessageType::kStatus, "r"))));
  try {
    bp::decode_request(bp::encode(bp::make_message(bp::MessageType::kStatusReply, "r7")));
    FAIL();
  } catch (const bp::ProtocolError& e) {
    EXPECT_EQ(e.code(), ErrorCode::kUnknownType);
    EXPECT_EQ(e.request_id().value_or(""), "r7");
  }
  EXPECT_THROW(bp::decode_request(bp::encode(bp::make_message(bp::MessageType::kEventStage, ""))),
               bp::ProtocolError);
}

TEST(Codec, DeeplyNestedJsonIsRefusedBeforeParsing) {
  const std::size_t depth = 30000;  // fits the 64 KiB header limit
  const std::string nested = std::string(depth, '[') + std::string(depth, ']');
  EXPECT_EQ(decode_error({nested}), ErrorCode::kTooLarge);
  EXPECT_EQ(decode_error({"{\"a\":" + nested + "}"}), ErrorCode::kTooLarge);
  // Found by fuzz_message: printing a deep "v" for the version error overflowed the stack.
  EXPECT_EQ(decode_error({"{\"v\":" + nested + R"(,"type":"status","request_id":"r"})"}), ErrorCode::kTooLarge);
}

TEST(Codec, NestingUpToTheLimitIsAccepted) {
  const bp::Limits limits;
  // The header object is level 1, so the field may nest max_header_depth - 1 levels.
  const std::size_t inner = limits.max_header_depth - 1;
  const std::string field = std::string(inner, '[') + std::string(inner, ']');
  const std::string ok = R"({"v":1,"type":"status","request_id":"r","x":)" + field + "}";
  EXPECT_EQ(bp::json_nesting_depth(ok), limits.max_header_depth);
  EXPECT_NO_THROW(bp::decode({ok}, limits));
  const std::string deeper = R"({"v":1,"type":"status","request_id":"r","x":[)" + field + "]}";
  EXPECT_EQ(decode_error({deeper}, limits), ErrorCode::kTooLarge);
}

TEST(Codec, NestingDepthSkipsBracketsInsideStrings) {
  EXPECT_EQ(bp::json_nesting_depth(R"({"a":"[[[{{{\"[["})"), 1u);
  EXPECT_EQ(bp::json_nesting_depth(R"([{"a":[1,{"b":[]}]}])"), 5u);
  EXPECT_EQ(bp::json_nesting_depth("42"), 0u);
}
