// The outputs table (protocol/result_outputs.h), one test per row: every name
// of a part leads back to it, and the columns the daemon acts on agree with
// each other (tests/server/test_server_core.cpp checks the daemon per row).
#include <gtest/gtest.h>

#include <set>

#include "protocol/result_outputs.h"
#include "protocol/timing_log.h"

namespace bp = brainshift::protocol;
using bp::ResultPart;

class OutputRow : public ::testing::TestWithParam<bp::ResultOutput> {};

TEST_P(OutputRow, EveryNameLeadsBackToItsPart) {
  const bp::ResultOutput& row = GetParam();
  EXPECT_EQ(bp::result_output(row.part).wire, row.wire) << "one row per part";
  EXPECT_EQ(bp::result_part_from_string(row.wire), row.part);
  EXPECT_EQ(bp::result_part_from_cli(row.cli), row.part);
  EXPECT_EQ(bp::to_string(row.part), row.wire);
  if (row.part == ResultPart::kModels) {
    EXPECT_EQ(bp::part_of_file(bp::model_file_name("brain")), ResultPart::kModels);
    EXPECT_EQ(bp::file_for_frame(bp::model_frame_name("brain")), bp::model_file_name("brain"));
    return;
  }
  EXPECT_EQ(bp::part_of_file(row.file), row.part);
  EXPECT_EQ(bp::part_of_file(row.stored), row.part);
  EXPECT_EQ(bp::file_for_frame(bp::frame_name(row.part)), row.file);
  EXPECT_EQ(bp::stored_file_names(row.part).front(), row.stored) << "the store's own name first";
}

TEST_P(OutputRow, DeferredPresenceAndRepairColumnsAgree) {
  const bp::ResultOutput& row = GetParam();
  // A deferred part is timed as the stage that makes it; a part of the answer has none.
  EXPECT_EQ(row.deferred, !row.deferred_stage.empty());
  if (row.deferred) {
    EXPECT_TRUE(bp::is_known_stage(bp::StageScope::kIntraop, row.deferred_stage)) << row.deferred_stage;
  }
  if (row.remade_from) {
    // Only a lost deferred part is made again, from a part stored with the answer.
    EXPECT_TRUE(row.deferred);
    EXPECT_FALSE(bp::result_output(*row.remade_from).deferred);
    EXPECT_TRUE(bp::part_expected(*row.remade_from, {}));
  }
  const bp::ScanFacts labels_only{false, true}, with_image{true, true}, image_only{true, false};
  // An image-only scan has every part: the engine made its segmentation.
  EXPECT_TRUE(bp::part_expected(row.part, image_only));
  EXPECT_TRUE(bp::why_not_expected(row.part, image_only).empty());
  switch (row.presence) {
    case bp::PartPresence::kEveryScan:
      EXPECT_TRUE(bp::part_expected(row.part, labels_only));
      EXPECT_TRUE(bp::part_expected(row.part, with_image));
      break;
    case bp::PartPresence::kWithIntraopImage:
      EXPECT_TRUE(bp::part_expected(row.part, with_image));
      EXPECT_FALSE(bp::part_expected(row.part, labels_only));
      EXPECT_EQ(bp::why_not_expected(row.part, labels_only), "no intraop image was pushed");
      break;
    case bp::PartPresence::kEngineSegmentation: {
      // Labels with their image are refined unless the push said exact.
      const bp::ScanFacts exact{true, true, true};
      EXPECT_TRUE(bp::part_expected(row.part, with_image));
      EXPECT_FALSE(bp::part_expected(row.part, exact));
      EXPECT_FALSE(bp::part_expected(row.part, labels_only));
      EXPECT_NE(bp::why_not_expected(row.part, exact).find("exact"), std::string::npos);
      EXPECT_NE(bp::why_not_expected(row.part, labels_only).find("no intraop image"), std::string::npos);
      break;
    }
  }
}

INSTANTIATE_TEST_SUITE_P(EveryRow, OutputRow, ::testing::ValuesIn(bp::kResultOutputs),
                         [](const ::testing::TestParamInfo<bp::ResultOutput>& info) {
                           return std::string(info.param.wire);
                         });

TEST(OutputTable, NoTwoRowsShareAName) {
  std::set<std::string_view> wire, cli, file, stored;
  for (const auto& row : bp::kResultOutputs) {
    EXPECT_TRUE(wire.insert(row.wire).second) << row.wire;
    EXPECT_TRUE(cli.insert(row.cli).second) << row.cli;
    EXPECT_TRUE(file.insert(row.file).second) << row.file;
    EXPECT_TRUE(stored.insert(row.stored).second) << row.stored;
  }
}
