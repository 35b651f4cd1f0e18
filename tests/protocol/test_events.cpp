// Events: every type survives the wire and carries a valid publication time.
#include <gtest/gtest.h>

#include "protocol/events.h"

namespace bp = brainshift::protocol;
using bp::ErrorCode;

namespace {
bp::Message wire_trip(const bp::Message& m) { return bp::decode(bp::encode(m)); }
}  // namespace

TEST(Events, EveryEventRoundTrips) {
  const bp::PreopProgressEvent progress{"p-1", "mesh", 0.25};
  EXPECT_EQ(bp::parse_preop_progress_event(wire_trip(bp::make_event(progress))), progress);
  const bp::PreopReadyEvent ready{"p-1", {43733, 215037}, 21.5};
  EXPECT_EQ(bp::parse_preop_ready_event(wire_trip(bp::make_event(ready))), ready);
  const bp::PreopFailedEvent failed{"p-1", {ErrorCode::kInvalidRequest, "labels grid differs from t1"}};
  EXPECT_EQ(bp::parse_preop_failed_event(wire_trip(bp::make_event(failed))), failed);
  const bp::StageEvent stage{{bp::StageScope::kIntraop, "s-1", "", "affine", 0.123, "2024-05-01T12:00:00.123Z"}};
  EXPECT_EQ(bp::parse_stage_event(wire_trip(bp::make_event(stage))), stage);
  const bp::ScanProgressEvent scan_progress{"s-1", "solve", 0.6};
  EXPECT_EQ(bp::parse_scan_progress_event(wire_trip(bp::make_event(scan_progress))), scan_progress);
  const bp::ScanDoneEvent done{"s-1", "c-1", 3.25, bp::ResultKindInfo{}};
  EXPECT_EQ(bp::parse_scan_done_event(wire_trip(bp::make_event(done))), done);
  const bp::ScanDoneEvent fallback{"s-2", std::nullopt, 1.5,
                                   bp::ResultKindInfo{bp::ResultKind::affine_only_fallback, "Jacobian folded"}};
  EXPECT_EQ(bp::parse_scan_done_event(wire_trip(bp::make_event(fallback))), fallback);
  const bp::ScanDoneEvent caution{"s-3", std::nullopt, 1.5,
                                  bp::ResultKindInfo{bp::ResultKind::nonrigid, "", "brain the given labels lack"}};
  EXPECT_EQ(bp::parse_scan_done_event(wire_trip(bp::make_event(caution))), caution);
  const bp::ScanFailedEvent scan_failed{"s-1", std::nullopt, "solve", {ErrorCode::kInternal, "solver diverged"}};
  EXPECT_EQ(bp::parse_scan_failed_event(wire_trip(bp::make_event(scan_failed))), scan_failed);
  const bp::ServerShutdownEvent bye{"admin request"};
  EXPECT_EQ(bp::parse_server_shutdown_event(wire_trip(bp::make_event(bye))), bye);
  const bp::ServerShutdownEvent silent{""};  // empty free text is allowed
  EXPECT_EQ(bp::parse_server_shutdown_event(wire_trip(bp::make_event(silent))), silent);
}

TEST(Events, HaveNoRequestIdAndAPublicationTime) {
  const auto m = wire_trip(bp::make_event(bp::ScanDoneEvent{"s-1", std::nullopt, 1.0}));
  EXPECT_EQ(m.request_id(), "");
  EXPECT_TRUE(bp::is_iso8601_utc(m.header.at("t").get<std::string>()));
  EXPECT_EQ(bp::kind_of(m.type()), bp::MessageKind::kEvent);
}

TEST(Events, ScanDoneCarriesTheResultKindAndReadsAnOlderServersWithout) {
  const auto m = bp::make_event(
      bp::ScanDoneEvent{"s-1", std::nullopt, 1.0, bp::ResultKindInfo{bp::ResultKind::affine_only_fallback, "why"}});
  EXPECT_EQ(m.header.at("kind"), "affine_only_fallback");
  EXPECT_EQ(m.header.at("fallback_reason"), "why");
  const auto nonrigid = bp::make_event(bp::ScanDoneEvent{"s-1", std::nullopt, 1.0, bp::ResultKindInfo{}});
  EXPECT_EQ(nonrigid.header.at("kind"), "nonrigid");
  EXPECT_FALSE(nonrigid.header.contains("fallback_reason"));
  EXPECT_FALSE(nonrigid.header.contains("caution"));
  // A caution (revision 6) rides beside a non-rigid kind; a server before it
  // sends none, read as no caution.
  const auto cautioned = bp::make_event(
      bp::ScanDoneEvent{"s-1", std::nullopt, 1.0, bp::ResultKindInfo{bp::ResultKind::nonrigid, "", "lobe lacking"}});
  EXPECT_EQ(cautioned.header.at("kind"), "nonrigid");
  EXPECT_EQ(cautioned.header.at("caution"), "lobe lacking");
  EXPECT_EQ(bp::parse_scan_done_event(nonrigid).result->caution, "");
  // A revision 1 server sends no kind (PROTOCOL.md 10): read as unknown.
  auto older = nonrigid;
  older.header.erase("kind");
  EXPECT_EQ(bp::parse_scan_done_event(older).result, std::nullopt);
  auto unknown = nonrigid;
  unknown.header["kind"] = "rigid";
  EXPECT_THROW(bp::parse_scan_done_event(unknown), bp::ProtocolError);
}

TEST(Events, ParsersRefuseWrongTypeBadFractionAndBadStageLine) {
  const auto done = bp::make_event(bp::ScanDoneEvent{"s-1", std::nullopt, 1.0});
  EXPECT_THROW(bp::parse_scan_failed_event(done), bp::ProtocolError);

  auto progress = bp::make_event(bp::ScanProgressEvent{"s-1", "solve", 0.5});
  progress.header["fraction"] = -0.1;
  EXPECT_THROW(bp::parse_scan_progress_event(progress), bp::ProtocolError);

  auto stage = bp::make_event(bp::StageEvent{{bp::StageScope::kIntraop, "s-1", "", "warp", 0.5, bp::utc_now()}});
  stage.header["timing"].erase("scan_id");
  EXPECT_THROW(bp::parse_stage_event(stage), bp::ProtocolError);

  auto stamped = bp::make_event(bp::ServerShutdownEvent{"x"});
  stamped.header["t"] = "yesterday";
  EXPECT_THROW(bp::parse_server_shutdown_event(stamped), bp::ProtocolError);
}
