// The timing-log line schema, the UTC time format and the timings frame.
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "protocol/timing_log.h"
#include "temp_dir.h"  // tests/support

namespace bp = brainshift::protocol;
using nlohmann::json;

TEST(TimingLog, LineHasTheDocumentedSchema) {
  const bp::StageTiming t{bp::StageScope::kIntraop, "s-000001", "", "affine", 0.123,
                          "2024-05-01T12:34:56.789Z"};
  const std::string line = bp::make_stage_log_line(t);
  EXPECT_EQ(line.find('\n'), std::string::npos);
  const json j = json::parse(line);
  EXPECT_EQ(j, (json{{"v", 1}, {"event", "stage"}, {"scope", "intraop"}, {"scan_id", "s-000001"},
                     {"stage", "affine"}, {"seconds", 0.123}, {"t", "2024-05-01T12:34:56.789Z"}}));
  EXPECT_EQ(bp::parse_stage_log_line(line), t);
}

TEST(TimingLog, PreopLinesNeedAPreopIdIntraopLinesAScanId) {
  const bp::StageTiming preop{bp::StageScope::kPreop, "", "p-1", "factorise", 4.5, bp::utc_now()};
  EXPECT_EQ(bp::parse_stage_log_line(bp::make_stage_log_line(preop)), preop);
  bp::StageTiming no_preop_id = preop;
  no_preop_id.preop_id.clear();
  EXPECT_THROW(bp::make_stage_log_line(no_preop_id), bp::ProtocolError);
  const bp::StageTiming no_scan{bp::StageScope::kIntraop, "", "", "solve", 0.1, bp::utc_now()};
  EXPECT_THROW(bp::make_stage_log_line(no_scan), bp::ProtocolError);
}

TEST(TimingLog, RefusesBadLines) {
  const std::string good =
      R"({"v":1,"event":"stage","scope":"intraop","scan_id":"s","stage":"solve","seconds":0.1,"t":"2024-01-01T00:00:00Z"})";
  EXPECT_NO_THROW(bp::parse_stage_log_line(good));
  auto broken = [&](const char* key, json value) {
    json j = json::parse(good);
    j[key] = value;
    return j.dump();
  };
  EXPECT_THROW(bp::parse_stage_log_line(broken("v", 2)), bp::ProtocolError);
  EXPECT_THROW(bp::parse_stage_log_line(broken("seconds", -1.0)), bp::ProtocolError);
  EXPECT_THROW(bp::parse_stage_log_line(broken("seconds", "fast")), bp::ProtocolError);
  EXPECT_THROW(bp::parse_stage_log_line(broken("stage", "Solve Now")), bp::ProtocolError);
  EXPECT_THROW(bp::parse_stage_log_line(broken("t", "2024-01-01 00:00:00")), bp::ProtocolError);
  EXPECT_THROW(bp::parse_stage_log_line(broken("scope", "postop")), bp::ProtocolError);
  EXPECT_THROW(bp::parse_stage_log_line("{"), bp::ProtocolError);
}

TEST(TimingLog, UtcFormatting) {
  using namespace std::chrono;
  const system_clock::time_point epoch_plus{milliseconds(1714566896789)};
  EXPECT_EQ(bp::format_utc(epoch_plus), "2024-05-01T12:34:56.789Z");
  EXPECT_EQ(bp::format_utc(system_clock::time_point{}), "1970-01-01T00:00:00.000Z");
  EXPECT_TRUE(bp::is_iso8601_utc(bp::utc_now()));
  EXPECT_FALSE(bp::is_iso8601_utc("2024-05-01T12:34:56+02:00"));
  EXPECT_TRUE(bp::is_iso8601_utc("2024-05-01T12:34:56Z"));
  EXPECT_TRUE(bp::is_iso8601_utc("2024-05-01T12:34:56.123456789Z"));
  EXPECT_FALSE(bp::is_iso8601_utc("2024-05-01T12:34:56.Z"));
  EXPECT_FALSE(bp::is_iso8601_utc("2024-05-01T12:34:56.1234567890Z"));
  EXPECT_FALSE(bp::is_iso8601_utc("2024-5-01T12:34:56Z"));
  EXPECT_FALSE(bp::is_iso8601_utc(""));
}

TEST(TimingLog, KnownStages) {
  EXPECT_TRUE(bp::is_known_stage(bp::StageScope::kPreop, "factorise"));
  EXPECT_FALSE(bp::is_known_stage(bp::StageScope::kPreop, "affine"));
  EXPECT_TRUE(bp::is_known_stage(bp::StageScope::kIntraop, "models"));
  EXPECT_TRUE(bp::is_known_stage(bp::StageScope::kIntraop, "refine"));
  // One vocabulary: the daemon's own stages and the preop's models are known too.
  for (const char* daemon_stage : {"decode", "outputs", "store", "metrics", "itk_field", "report"})
    EXPECT_TRUE(bp::is_known_stage(bp::StageScope::kIntraop, daemon_stage)) << daemon_stage;
  EXPECT_TRUE(bp::is_known_stage(bp::StageScope::kPreop, "models"));
  EXPECT_FALSE(bp::is_known_stage(bp::StageScope::kIntraop, "atlas"));
}

TEST(TimingLog, FileGetsOneLinePerStage) {
  const brainshift::test::TempDir dir("timing");
  const auto path = dir / "timing.jsonl";
  {
    bp::TimingLogFile log(path.string());
    log.write({bp::StageScope::kIntraop, "s-1", "", "read", 0.01, bp::utc_now()});
    log.write({bp::StageScope::kIntraop, "s-1", "", "affine", 0.2, bp::utc_now()});
  }
  std::ifstream in(path);
  std::string line;
  std::vector<std::string> stages;
  while (std::getline(in, line)) stages.push_back(bp::parse_stage_log_line(line).stage);
  EXPECT_EQ(stages, (std::vector<std::string>{"read", "affine"}));
  EXPECT_THROW(bp::TimingLogFile("/nonexistent-dir/x.jsonl"), std::runtime_error);
}

TEST(ScanTimingsJson, RoundTripAndSchema) {
  bp::ScanTimings t;
  t.preop = {1.5, 9.8, 2.0, 4.5, 17.8};
  t.intraop = {0.2, 0.5, 0.3, 0.1, 0.4, 0.6, 0.7, 2.8};
  t.mesh = {43733, 215037};
  const std::string text = bp::make_timings_json(t);
  const json j = json::parse(text);
  EXPECT_EQ(j["preop"].size(), 5u);
  EXPECT_EQ(j["intraop"].size(), 8u);
  EXPECT_EQ(j["mesh"]["tets"], 215037);
  EXPECT_EQ(bp::parse_timings_json(text), t);
  json missing = j;
  missing["intraop"].erase("solve");
  EXPECT_THROW(bp::parse_timings_json(missing.dump()), bp::ProtocolError);
}
