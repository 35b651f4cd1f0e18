// Request handling through ServerCore with the engine double: every reply is
// checked for its type or its typed error, and the server keeps serving.
#include <gtest/gtest.h>

#include <algorithm>
#include <mutex>

#include "image/nifti_io.h"
#include "protocol/events.h"
#include "protocol/media.h"
#include "server/case_store.h"
#include "server/server_core.h"
#include "test_support.h"

using namespace brainshift;
using namespace brainshift::server;
using namespace brainshift::protocol;
using namespace std::chrono_literals;
namespace fs = std::filesystem;

namespace {

struct Harness {
  test::TempDir dir;
  ServerSettings settings;
  std::unique_ptr<CaseStore> store;
  test::FakeEngine engine;
  std::mutex events_mutex;
  std::vector<Message> events;
  std::unique_ptr<ServerCore> core;

  explicit Harness(std::size_t queue_depth = 4) {
    settings.store = dir.path() / "store";
    settings.queue_depth = queue_depth;
    settings.preop.kind = DefaultPreop::Kind::none;
    open();
  }
  void open() {
    core.reset();
    store = std::make_unique<CaseStore>(settings.store);
    core = std::make_unique<ServerCore>(settings, *store, engine, [this](Message m) {
      std::lock_guard lock(events_mutex);
      events.push_back(std::move(m));
    });
    core->start();
  }
  Message call(const Message& request) { return core->handle_wire(encode(request)); }
  int count_events(MessageType type) {
    std::lock_guard lock(events_mutex);
    int n = 0;
    for (const auto& e : events) n += e.type() == type;
    return n;
  }
  std::string load_preop(std::optional<std::string> patient_id = std::nullopt) {
    PreopLoadRequest r;
    r.patient_id = std::move(patient_id);
    const LabelImage labels = test::ball_labels(10);
    r.t1 = media::nifti_frame("t1", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true));
    r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, false));
    const Message reply = call(make_preop_load_request("p1", r));
    EXPECT_EQ(reply.type(), MessageType::kPreopLoadReply) << reply.header.dump();
    EXPECT_TRUE(core->step(10ms));
    return parse_preop_load_reply(reply).preop_id;
  }
  Message push(const LabelImage& labels, std::optional<std::string> client_id = std::nullopt, bool image = false,
               std::optional<std::string> labels_use = std::nullopt) {
    ScanPushRequest r;
    r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, true));
    if (image) r.image = media::nifti_frame("image", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true));
    r.client_scan_id = client_id;
    r.labels_use = std::move(labels_use);
    return call(make_scan_push_request("push", r));
  }
  // An image alone on this grid (the engine segments it).
  Message push_image(const Grid3& grid, std::optional<std::string> client_id = std::nullopt) {
    ScanPushRequest r;
    r.image = media::nifti_frame("image", scalar_image_to_bytes(test::ramp_image(grid), VoxelType::float32, true));
    r.client_scan_id = client_id;
    return call(make_scan_push_request("push", r));
  }
};

void expect_error(const Message& reply, ErrorCode code, const std::string& request_id = "") {
  ASSERT_EQ(reply.type(), MessageType::kError) << reply.header.dump();
  EXPECT_EQ(parse_error_reply(reply).code, code) << reply.header.dump();
  if (!request_id.empty()) {
    EXPECT_EQ(reply.request_id(), request_id);
  }
}

LabelImage intraop_labels(int n = 12) {
  LabelImage l = test::ball_labels(n);
  return l;
}

// Each kind of scan scan.push takes: labels, labels and image, image alone.
constexpr ScanFacts kScanKinds[] = {{false, true}, {true, true}, {true, true, true}, {true, false}};
std::string describe(const ScanFacts& kind) {
  return !kind.has_labels    ? "image alone"
         : !kind.has_image   ? "labels only"
         : kind.labels_exact ? "labels and image, used exactly"
                             : "labels and image, refined";
}
Message push_kind(Harness& h, const ScanFacts& kind) {
  if (!kind.has_labels) return h.push_image(intraop_labels().grid);
  return h.push(intraop_labels(), std::nullopt, kind.has_image,
                kind.labels_exact ? std::optional<std::string>("exact") : std::nullopt);
}

}  // namespace

TEST(ServerCore, IdleServerAnswersStatusAndRefusesScans) {
  Harness h;
  const StatusReply s = parse_status_reply(h.call(make_status_request("s1")));
  EXPECT_EQ(s.state, ServerState::kIdle);
  EXPECT_EQ(s.versions.at("protocol"), "1");
  EXPECT_EQ(s.queue.capacity, 4u);
  expect_error(h.push(intraop_labels()), ErrorCode::kNotReady, "push");
  EXPECT_TRUE(h.store->list_newest_first(10).empty());
}

TEST(ServerCore, PreopLoadWarmsUpAndIsStoredWithItsMesh) {
  Harness h;
  const std::string id = h.load_preop();
  const StatusReply s = parse_status_reply(h.call(make_status_request("s")));
  EXPECT_EQ(s.state, ServerState::kReady);
  EXPECT_EQ(s.preop_id.value(), id);
  EXPECT_EQ(s.mesh->nodes, 5u);
  EXPECT_EQ(s.mesh->tets, 2u);
  EXPECT_EQ(h.count_events(MessageType::kEventPreopReady), 1);
  EXPECT_GE(h.count_events(MessageType::kEventPreopProgress), 2);
  EXPECT_EQ(h.count_events(MessageType::kEventStage), 1);  // "mesh" finished
  EXPECT_EQ(h.store->load_preop().preop_id, id);
  EXPECT_TRUE(h.store->load_mesh(id));
}

TEST(ServerCore, PreopWithLabelTableIsMappedToEngineLabels) {
  Harness h;
  PreopLoadRequest r;
  LabelImage labels = test::ball_labels(10);
  for (auto& v : labels.voxels) v = v == 1 ? 17 : (v == 2 ? 43 : 0);
  r.t1 = media::nifti_frame("t1", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true));
  r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, false));
  protocol::LabelMap table;
  table.structures["brain"] = {17};
  table.structures["ventricles"] = {43};
  r.label_table = media::json_frame("label_table", make_label_map_json(table));
  EXPECT_EQ(h.call(make_preop_load_request("p", r)).type(), MessageType::kPreopLoadReply);
  ASSERT_TRUE(h.core->step(10ms));
  const LabelImage& seen = h.engine.last_preop.labels;
  for (std::size_t i = 0; i < seen.voxels.size(); ++i)
    ASSERT_EQ(seen.voxels[i], labels.voxels[i] == 17 ? 1 : (labels.voxels[i] == 43 ? 2 : 0));
}

// A daemon configured with a fifth structure: a preop naming it in its label
// map is mapped to the daemon's values, a map naming a structure the daemon
// does not know is refused naming it, and the intraop labels of a scan use the
// sender's values too (PROTOCOL.md), mapped the same way before the engine
// sees them.
TEST(ServerCore, LabelMapWithAFifthStructureFlowsToPreopAndScans) {
  Harness h;
  LabelEntry arcuate;
  arcuate.value = 5;
  arcuate.name = "arcuate_fasciculus";
  arcuate.short_name = "af";
  h.engine.table.entries.push_back(arcuate);
  LabelImage labels = test::ball_labels(10);
  for (std::size_t i = 0; i < labels.voxels.size(); ++i)
    labels.voxels[i] = labels.voxels[i] == 2 ? 43 : labels.voxels[i] == 1 ? (i % 7 == 0 ? 99 : 17) : 0;
  PreopLoadRequest r;
  r.t1 = media::nifti_frame("t1", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true));
  r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, false));
  protocol::LabelMap map;
  map.structures["brain"] = {17};
  map.structures["ventricles"] = {43};
  map.structures["liver"] = {99};
  r.label_table = media::json_frame("label_table", make_label_map_json(map));
  const Message refused = h.call(make_preop_load_request("p0", r));
  expect_error(refused, ErrorCode::kInvalidRequest, "p0");
  EXPECT_NE(parse_error_reply(refused).message.find("\"liver\" is not in the daemon's label table"),
            std::string::npos) << parse_error_reply(refused).message;

  map.structures.erase("liver");
  map.structures["arcuate_fasciculus"] = {99};
  r.label_table = media::json_frame("label_table", make_label_map_json(map));
  ASSERT_EQ(h.call(make_preop_load_request("p1", r)).type(), MessageType::kPreopLoadReply);
  ASSERT_TRUE(h.core->step(10ms));
  auto engine_value = [](std::uint16_t v) -> std::uint16_t { return v == 17 ? 1 : v == 43 ? 2 : v == 99 ? 5 : 0; };
  const LabelImage& seen = h.engine.last_preop.labels;
  for (std::size_t i = 0; i < seen.voxels.size(); ++i) ASSERT_EQ(seen.voxels[i], engine_value(labels.voxels[i])) << i;

  // The double's field holds the label value the engine got in x.
  const ScanPushReply pushed = parse_scan_push_reply(h.push(labels));
  ASSERT_TRUE(h.core->step(10ms));
  const ScanResultReply result = parse_scan_result_reply(
      h.call(make_scan_result_request("r", {pushed.scan_id, {ResultPart::kDisplacement}, {}})));
  const VectorImage3 field = vector_image_from_bytes(result.find("displacement")->bytes, "field", 1u << 26);
  for (std::size_t i = 0; i < field.vectors.size(); ++i)
    ASSERT_EQ(field.vectors[i].x(), engine_value(labels.voxels[i])) << i;

  // A sender value the map does not list fails the scan, naming it.
  LabelImage stray = labels;
  stray.voxels[stray.voxels.size() / 2] = 123;
  const ScanPushReply bad = parse_scan_push_reply(h.push(stray));
  ASSERT_TRUE(h.core->step(10ms));
  const Message failed = h.call(make_scan_result_request("r2", {bad.scan_id, {ResultPart::kDisplacement}, {}}));
  ASSERT_EQ(failed.type(), MessageType::kError);
  EXPECT_NE(parse_error_reply(failed).message.find("value 123 is not in the label table"), std::string::npos)
      << parse_error_reply(failed).message;
}

// labels.get serves the engine's table as configured (here a renamed,
// recoloured parenchyma and a fifth structure without a model), before any
// preop: a viewer names and colours its scene with it.
TEST(ServerCore, LabelsGetServesTheDaemonsLabelTable) {
  Harness h;
  h.engine.table.entries.front().name = "cerebrum";
  h.engine.table.entries.front().colour = {192, 128, 64};
  LabelEntry arcuate;
  arcuate.value = 5;
  arcuate.name = "arcuate_fasciculus";
  arcuate.make_model = false;
  h.engine.table.entries.push_back(arcuate);
  const LabelsReply r = parse_labels_reply(h.call(make_labels_request("g")));
  ASSERT_EQ(r.labels.size(), h.engine.table.entries.size());
  EXPECT_EQ(r.labels.front(), (LabelInfo{1, "cerebrum", "cerebrum", "parenchyma", {192, 128, 64}, true}));
  EXPECT_EQ(r.labels.back(), (LabelInfo{5, "arcuate_fasciculus", "arcuate_fas", "structure", arcuate.colour, false}));
  for (std::size_t i = 0; i < r.labels.size(); ++i) {
    EXPECT_EQ(r.labels[i].value, h.engine.table.entries[i].value);
    EXPECT_EQ(r.labels[i].role, to_string(h.engine.table.entries[i].role));
  }
  // A frame is refused, and the server keeps serving.
  Message with_frame = make_labels_request("g2");
  with_frame.frames.push_back(media::json_frame("labels", "{}"));
  expect_error(h.call(with_frame), ErrorCode::kInvalidRequest, "g2");
  EXPECT_EQ(parse_status_reply(h.call(make_status_request("s"))).state, ServerState::kIdle);
}

TEST(ServerCore, BadPreopIsATypedErrorAndNothingChanges) {
  Harness h;
  PreopLoadRequest r;
  LabelImage labels = test::ball_labels(10);
  labels.voxels[0] = 9;  // not a default label, no table
  r.t1 = media::nifti_frame("t1", scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true));
  r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, false));
  expect_error(h.call(make_preop_load_request("bad1", r)), ErrorCode::kInvalidRequest, "bad1");
  r.labels = media::nifti_frame("labels", "\x1f\x8b garbage that is not gzip");
  expect_error(h.call(make_preop_load_request("bad2", r)), ErrorCode::kInvalidRequest, "bad2");
  // Half a voxel off the T1's grid (a box of it shifted by whole voxels
  // would be placed on it: image/label_placement.h).
  LabelImage other = test::ball_labels(10);
  other.grid.world_from_voxel.col(3) += 0.5 * other.grid.world_from_voxel.col(0);
  r.labels = media::nifti_frame("labels", label_image_to_bytes(other, false));
  expect_error(h.call(make_preop_load_request("bad3", r)), ErrorCode::kInvalidRequest, "bad3");
  EXPECT_EQ(parse_status_reply(h.call(make_status_request("s"))).state, ServerState::kIdle);
  EXPECT_FALSE(h.store->has_preop());
}

TEST(ServerCore, FailedWarmUpIsReportedInStatusAndEvents) {
  Harness h;
  h.engine.fail_preop = true;
  PreopLoadRequest r;
  r.use_default_atlas = true;
  EXPECT_EQ(h.call(make_preop_load_request("p", r)).type(), MessageType::kPreopLoadReply);
  EXPECT_EQ(parse_status_reply(h.call(make_status_request("s"))).state, ServerState::kLoadingPreop);
  ASSERT_TRUE(h.core->step(10ms));
  const StatusReply s = parse_status_reply(h.call(make_status_request("s")));
  EXPECT_EQ(s.state, ServerState::kIdle);
  ASSERT_TRUE(s.last_error);
  EXPECT_EQ(s.last_error->code, ErrorCode::kInvalidRequest);
  EXPECT_EQ(h.count_events(MessageType::kEventPreopFailed), 1);
  EXPECT_FALSE(h.store->has_preop());
}

TEST(ServerCore, PushRunPullReturnsExactlyTheEngineOutput) {
  Harness h;
  h.load_preop();
  const LabelImage labels = intraop_labels();
  const Message reply = h.push(labels, std::string("scanner-7"), true);
  ASSERT_EQ(reply.type(), MessageType::kScanPushReply) << reply.header.dump();
  const ScanPushReply pushed = parse_scan_push_reply(reply);
  EXPECT_FALSE(pushed.duplicate);
  // Acknowledged means stored.
  EXPECT_EQ(h.store->find(pushed.scan_id)->state, StoredScanState::queued);
  expect_error(h.call(make_scan_result_request("r0", {pushed.scan_id, {ResultPart::kDisplacement}, {}})),
               ErrorCode::kNotReady, "r0");
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_EQ(h.count_events(MessageType::kEventScanDone), 1);

  ScanResultRequest req{pushed.scan_id,
                        {ResultPart::kDisplacement, ResultPart::kWarpedImage, ResultPart::kWarpedLabels,
                         ResultPart::kModels, ResultPart::kMetrics, ResultPart::kTimings},
                        {}};
  const Message result = h.call(make_scan_result_request("r1", req));
  ASSERT_EQ(result.type(), MessageType::kScanResultReply) << result.header.dump();
  const ScanResultReply r = parse_scan_result_reply(result);
  const auto expected = test::FakeEngine::files_for(labels);
  EXPECT_EQ(r.find("displacement")->bytes, expected.at("field.nii"));
  EXPECT_EQ(r.find("displacement")->media_type, media::kNifti);  // stored plain, sent as such
  EXPECT_EQ(r.find("warped_image")->bytes, expected.at("warped_image.nii.gz"));
  EXPECT_EQ(r.find("warped_labels")->bytes, expected.at("warped_labels.nii.gz"));
  EXPECT_EQ(r.find("model.brain")->bytes, expected.at("models/brain.vtp"));
  EXPECT_EQ(r.find("metrics")->bytes, expected.at("metrics.json"));
  EXPECT_EQ(r.find("timings")->bytes, expected.at("timings.json"));
  // The engine wrote no ventricle/tract/tumor model and no ITK file: said so.
  EXPECT_EQ(r.unavailable.size(), 3u);
  EXPECT_EQ(r.find("model.ventricles"), nullptr);

  const ScanListReply list = parse_scan_list_reply(h.call(make_scan_list_request("l")));
  ASSERT_EQ(list.scans.size(), 1u);
  EXPECT_EQ(list.scans[0].state, ScanState::kDone);
  EXPECT_EQ(list.scans[0].client_scan_id.value(), "scanner-7");
  // Timing log: one line per finished stage.
  EXPECT_TRUE(fs::exists(h.settings.timing_log_path()));
  EXPECT_GE(h.count_events(MessageType::kEventStage), 4);  // mesh, read, affine, solve
}

TEST(ServerCore, ReportIsRenderedAfterScanDoneAndServedAsAPart) {
  Harness h;
  h.load_preop();
  const std::string id = parse_scan_push_reply(h.push(intraop_labels(), std::nullopt, true)).scan_id;
  const ScanResultRequest want_report{id, {ResultPart::kReport, ResultPart::kTimings}, {}};
  const ScanResultRequest want_itk{id, {ResultPart::kDisplacementItk}, {}};
  std::optional<ScanResultReply> itk_during;
  // While the report renders, the scan is already done: the other parts are
  // served and the report is "pending", not refused.
  std::optional<ScanResultReply> during;
  int done_events_during = 0;
  h.engine.while_rendering_report = [&] {
    done_events_during = h.count_events(MessageType::kEventScanDone);
    during = parse_scan_result_reply(h.call(make_scan_result_request("r-during", want_report)));
  };
  h.engine.while_rendering_deferred = [&] {  // before field.h5 and metrics.json
    itk_during = parse_scan_result_reply(h.call(make_scan_result_request("i-during", want_itk)));
  };
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_EQ(done_events_during, 1) << "scan.done must be announced before the report is rendered";
  ASSERT_TRUE(during);
  EXPECT_NE(during->find("timings"), nullptr);
  EXPECT_EQ(during->find("report"), nullptr);
  ASSERT_EQ(during->unavailable.size(), 1u);
  EXPECT_EQ(during->unavailable[0].part, "report");
  EXPECT_TRUE(during->unavailable[0].pending);
  // field.h5 is deferred the same way.
  ASSERT_EQ(itk_during->unavailable.size(), 1u);
  EXPECT_TRUE(itk_during->unavailable[0].pending);
  const ScanResultReply itk_after = parse_scan_result_reply(h.call(make_scan_result_request("i-after", want_itk)));
  EXPECT_TRUE(itk_after.unavailable.empty());
  EXPECT_NE(itk_after.find("displacement_itk"), nullptr);

  const ScanResultReply after = parse_scan_result_reply(h.call(make_scan_result_request("r-after", want_report)));
  ASSERT_NE(after.find("report"), nullptr);
  EXPECT_EQ(after.find("report")->media_type, media::kPng);
  EXPECT_EQ(after.find("report")->bytes, test::FakeEngine::kReportPng);
  EXPECT_TRUE(after.unavailable.empty());

  // It is durable: a restarted server on the same store serves it too.
  h.engine = test::FakeEngine{};
  h.open();
  const ScanResultReply restarted = parse_scan_result_reply(h.call(make_scan_result_request("r-restart", want_report)));
  ASSERT_NE(restarted.find("report"), nullptr);
  EXPECT_EQ(restarted.find("report")->bytes, test::FakeEngine::kReportPng);
}

TEST(ServerCore, ReportWithoutIntraopImageIsUnavailableForGood) {
  Harness h;
  h.load_preop();
  const std::string id = parse_scan_push_reply(h.push(intraop_labels())).scan_id;
  ASSERT_TRUE(h.core->step(10ms));
  const ScanResultReply r =
      parse_scan_result_reply(h.call(make_scan_result_request("r", {id, {ResultPart::kReport}, {}})));
  EXPECT_TRUE(r.frames.empty());
  ASSERT_EQ(r.unavailable.size(), 1u);
  EXPECT_EQ(r.unavailable[0].part, "report");
  EXPECT_FALSE(r.unavailable[0].pending);
  EXPECT_NE(r.unavailable[0].reason.find("no intraop image"), std::string::npos) << r.unavailable[0].reason;
}

TEST(ServerCore, IdempotentPushAndConflict) {
  Harness h;
  h.load_preop();
  const LabelImage labels = intraop_labels();
  const auto first = parse_scan_push_reply(h.push(labels, std::string("c1")));
  const auto again = parse_scan_push_reply(h.push(labels, std::string("c1")));
  EXPECT_EQ(first.scan_id, again.scan_id);
  EXPECT_TRUE(again.duplicate);
  LabelImage other = labels;
  other.voxels[5] = 2;
  expect_error(h.push(other, std::string("c1")), ErrorCode::kConflict, "push");
  EXPECT_EQ(h.store->list_newest_first(10).size(), 1u);
}

// A scan of another patient (a series sent from the wrong exam, a preop
// loaded for the wrong case) is refused before it is stored, whatever its
// images would register to; the same patient, or a scan that names none
// (NIfTI from a converter), is taken; the preop's patient survives a restart.
TEST(ServerCore, AScanOfAnotherPatientIsRefusedAndNotStored) {
  Harness h;
  h.load_preop(std::string("MRN-0042"));
  EXPECT_EQ(parse_status_reply(h.call(make_status_request("s"))).preop_patient_id.value_or(""), "MRN-0042");
  const LabelImage labels = intraop_labels();
  ScanPushRequest r;
  r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, true));
  r.patient_id = "MRN-0043";
  r.client_scan_id = "other-patient";
  const Message refused = h.call(make_scan_push_request("x", r));
  expect_error(refused, ErrorCode::kInvalidRequest, "x");
  EXPECT_NE(parse_error_reply(refused).message.find("MRN-0043"), std::string::npos);
  EXPECT_NE(parse_error_reply(refused).message.find("NOT stored"), std::string::npos);
  EXPECT_TRUE(h.store->list_newest_first(10).empty());
  EXPECT_FALSE(h.store->find_by_client_id("other-patient"));
  // DICOM pads PatientID with spaces: not significant.
  r.patient_id = "MRN-0042 ";
  r.client_scan_id = "same-patient";
  EXPECT_EQ(h.call(make_scan_push_request("y", r)).type(), MessageType::kScanPushReply);
  r.patient_id.reset();
  r.client_scan_id = "no-patient";
  EXPECT_EQ(h.call(make_scan_push_request("z", r)).type(), MessageType::kScanPushReply);
  EXPECT_EQ(h.store->list_newest_first(10).size(), 2u);
  ASSERT_TRUE(h.core->step(10ms));
  // After a restart the stored preop still names its patient.
  h.engine = test::FakeEngine{};
  h.open();
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_EQ(parse_status_reply(h.call(make_status_request("s"))).preop_patient_id.value_or(""), "MRN-0042");
  r.patient_id = "MRN-0043";
  r.client_scan_id = "other-patient";
  expect_error(h.call(make_scan_push_request("x2", r)), ErrorCode::kInvalidRequest, "x2");
  EXPECT_EQ(h.store->list_newest_first(10).size(), 2u);
}

TEST(ServerCore, FullQueueAnswersBusyAndStoresNothing) {
  Harness h(2);
  h.load_preop();
  const LabelImage labels = intraop_labels();
  EXPECT_EQ(h.push(labels).type(), MessageType::kScanPushReply);
  EXPECT_EQ(h.push(labels).type(), MessageType::kScanPushReply);
  expect_error(h.push(labels), ErrorCode::kBusy, "push");
  EXPECT_EQ(h.store->list_newest_first(10).size(), 2u);
  EXPECT_EQ(parse_status_reply(h.call(make_status_request("s"))).queue.depth, 2u);
  // A preop.load would swap the preop under queued scans: refused as busy.
  PreopLoadRequest atlas;
  atlas.use_default_atlas = true;
  expect_error(h.call(make_preop_load_request("p2", atlas)), ErrorCode::kBusy, "p2");
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_EQ(h.push(labels).type(), MessageType::kScanPushReply);
}

TEST(ServerCore, BadScansAreTypedErrorsAndTheServerKeepsServing) {
  Harness h;
  h.load_preop();
  ScanPushRequest r;
  r.labels = media::nifti_frame("labels", std::string(400, 'x'));
  expect_error(h.call(make_scan_push_request("b1", r)), ErrorCode::kInvalidRequest, "b1");
  const LabelImage labels = intraop_labels();
  r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, false));
  r.image = media::nifti_frame("image", scalar_image_to_bytes(test::ramp_image(test::small_grid(7)), VoxelType::float32, false));
  expect_error(h.call(make_scan_push_request("b2", r)), ErrorCode::kInvalidRequest, "b2");
  ScanPushRequest image_alone;  // an image alone that does not decode
  image_alone.image = media::nifti_frame("image", std::string(400, 'x'));
  expect_error(h.call(make_scan_push_request("b3", image_alone)), ErrorCode::kInvalidRequest, "b3");
  expect_error(h.call(make_scan_push_request("b4", ScanPushRequest{})), ErrorCode::kInvalidRequest, "b4");
  EXPECT_TRUE(h.store->list_newest_first(10).empty());

  // Protocol-level garbage.
  expect_error(h.core->handle_wire({"not json"}), ErrorCode::kMalformedJson);
  expect_error(h.core->handle_wire({R"({"v":2,"type":"status","request_id":"x","frames":[]})"}),
               ErrorCode::kVersionMismatch, "x");
  expect_error(h.core->handle_wire({R"({"v":1,"type":"scan.teleport","request_id":"y","frames":[]})"}),
               ErrorCode::kUnknownType, "y");
  expect_error(h.core->handle_wire({R"({"v":1,"type":"status","request_id":"z","frames":[]})", "extra"}),
               ErrorCode::kFrameCountMismatch, "z");
  // A reply type sent as a request.
  expect_error(h.call(make_shutdown_reply("w")), ErrorCode::kUnknownType, "w");
  expect_error(h.call(make_scan_result_request("nf", {"scan-999999", {ResultPart::kMetrics}, {}})),
               ErrorCode::kNotFound, "nf");
  // Still serving.
  EXPECT_EQ(h.call(make_status_request("ok")).type(), MessageType::kStatusReply);
  EXPECT_EQ(h.push(labels).type(), MessageType::kScanPushReply);
}

TEST(ServerCore, OversizedFrameIsRefused) {
  Harness h;
  h.settings.max_frame_bytes = 4096;
  h.open();
  h.load_preop();
  ScanPushRequest r;
  r.labels = media::nifti_frame("labels", label_image_to_bytes(intraop_labels(20), false));
  expect_error(h.call(make_scan_push_request("big", r)), ErrorCode::kTooLarge);
}

TEST(ServerCore, ResultKindTravelsWithScanDoneTheResultAndTheListBeforeTheMetrics) {
  Harness h;
  h.load_preop();
  h.engine.fallback_next_scan = true;
  const auto id = parse_scan_push_reply(h.push(intraop_labels(), std::string("fb"))).scan_id;
  std::optional<ScanResultReply> during;
  std::optional<ScanListReply> listed;
  h.engine.while_rendering_deferred = [&] {  // metrics.json not made yet
    during = parse_scan_result_reply(h.call(make_scan_result_request("r", {id, {ResultPart::kMetrics}, {}})));
    listed = parse_scan_list_reply(h.call(make_scan_list_request("l")));
  };
  ASSERT_TRUE(h.core->step(10ms));
  const ResultKindInfo fallback{ResultKind::affine_only_fallback, "fake: surface match diverged"};
  {
    std::lock_guard lock(h.events_mutex);
    const auto done = std::find_if(h.events.begin(), h.events.end(),
                                   [](const Message& e) { return e.type() == MessageType::kEventScanDone; });
    ASSERT_NE(done, h.events.end());
    EXPECT_EQ(parse_scan_done_event(*done).result, fallback);
  }
  ASSERT_TRUE(during.has_value());
  EXPECT_EQ(during->result, fallback);
  ASSERT_EQ(during->unavailable.size(), 1u);
  EXPECT_TRUE(during->unavailable[0].pending);
  EXPECT_EQ(listed->scans.at(0).result, fallback);
  // Stored with the result: the same after the metrics, from the store.
  EXPECT_EQ(h.store->find(id)->result, fallback);
  const auto after = parse_scan_result_reply(h.call(make_scan_result_request("r", {id, {ResultPart::kMetrics}, {}})));
  EXPECT_EQ(after.result, fallback);
  EXPECT_NE(after.find("metrics"), nullptr);
  // A non-rigid result says so too.
  const auto id2 = parse_scan_push_reply(h.push(intraop_labels())).scan_id;
  ASSERT_TRUE(h.core->step(10ms));
  const auto second = parse_scan_result_reply(h.call(make_scan_result_request("r", {id2, {ResultPart::kTimings}, {}})));
  EXPECT_EQ(second.result, ResultKindInfo{});
}

TEST(ServerCore, EngineFailureIsStoredReportedAndServedAsScanFailed) {
  Harness h;
  h.load_preop();
  h.engine.fail_next_scan = true;
  const auto id = parse_scan_push_reply(h.push(intraop_labels(), std::string("f1"))).scan_id;
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_EQ(h.count_events(MessageType::kEventScanFailed), 1);
  expect_error(h.call(make_scan_result_request("r", {id, {ResultPart::kDisplacement}, {}})), ErrorCode::kScanFailed, "r");
  const auto list = parse_scan_list_reply(h.call(make_scan_list_request("l")));
  EXPECT_EQ(list.scans.at(0).state, ScanState::kFailed);
  EXPECT_EQ(list.scans.at(0).error->code, ErrorCode::kScanFailed);
  // The next scan runs normally.
  const auto id2 = parse_scan_push_reply(h.push(intraop_labels())).scan_id;
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_EQ(h.store->find(id2)->state, StoredScanState::done);
}

TEST(ServerCore, RestartRestoresPreopMeshQueueAndResults) {
  Harness h;
  const std::string preop = h.load_preop();
  const LabelImage labels = intraop_labels();
  const auto done_id = parse_scan_push_reply(h.push(labels)).scan_id;
  ASSERT_TRUE(h.core->step(10ms));
  const auto pending_id = parse_scan_push_reply(h.push(labels, std::string("late"))).scan_id;
  const Message before = h.call(make_scan_result_request("r", {done_id, {ResultPart::kDisplacement}, {}}));

  // "Restart": a new core and a cold engine on the same store.
  h.engine = test::FakeEngine{};
  h.open();
  EXPECT_EQ(parse_status_reply(h.call(make_status_request("s"))).state, ServerState::kLoadingPreop);
  ASSERT_TRUE(h.core->step(10ms));  // warm-up from the store
  ASSERT_TRUE(h.engine.last_stored_mesh) << "the stored mesh must be reused, never re-meshed";
  EXPECT_EQ(h.engine.last_stored_mesh->tets, test::two_tet_mesh().tets);
  const StatusReply s = parse_status_reply(h.call(make_status_request("s")));
  EXPECT_EQ(s.state, ServerState::kReady);
  EXPECT_EQ(s.preop_id.value(), preop);
  EXPECT_EQ(s.queue.depth, 1u);
  const Message after = h.call(make_scan_result_request("r", {done_id, {ResultPart::kDisplacement}, {}}));
  EXPECT_EQ(parse_scan_result_reply(after).find("displacement")->bytes,
            parse_scan_result_reply(before).find("displacement")->bytes);
  ASSERT_TRUE(h.core->step(10ms));  // the acknowledged scan is run again
  EXPECT_EQ(h.store->find(pending_id)->state, StoredScanState::done);
  EXPECT_EQ(h.engine.scans_run, 1);
  // Idempotence survives the restart.
  EXPECT_TRUE(parse_scan_push_reply(h.push(labels, std::string("late"))).duplicate);
}

// Revision 4: an image alone is a scan. It is stored as such (no labels),
// registered without labels, its segmentation served, its idempotence key
// bound to the image's bytes, and after a restart it runs again from the
// stored image alone.
TEST(ServerCore, AnImageAloneIsStoredRegisteredServedAndRunAgainAfterARestart) {
  Harness h;
  h.load_preop();
  const Grid3 grid = intraop_labels().grid;
  const Message reply = h.push_image(grid, std::string("img-1"));
  ASSERT_EQ(reply.type(), MessageType::kScanPushReply) << reply.header.dump();
  const std::string id = parse_scan_push_reply(reply).scan_id;
  EXPECT_FALSE(h.store->find(id)->has_labels);
  EXPECT_TRUE(h.store->find(id)->has_image);
  EXPECT_FALSE(h.store->load_scan_input(id).labels_bytes.has_value());
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_FALSE(h.engine.last_scan_had_labels);
  const ScanResultReply r = parse_scan_result_reply(h.call(make_scan_result_request(
      "r", {id, {ResultPart::kIntraopLabels, ResultPart::kSegmentationConfidence, ResultPart::kWarpedLabels}, {}})));
  ASSERT_NE(r.find("intraop_labels"), nullptr);
  const LabelImage seg = label_image_from_bytes(r.find("intraop_labels")->bytes, "intraop_labels", 1u << 26);
  EXPECT_EQ(seg.voxels, h.engine.fake_segmentation(test::ramp_image(grid)).voxels);
  EXPECT_NE(r.find("segmentation_confidence"), nullptr);
  EXPECT_TRUE(r.unavailable.empty());

  // The same image under the same key: the same scan. Labels added to it: other data.
  EXPECT_TRUE(parse_scan_push_reply(h.push_image(grid, std::string("img-1"))).duplicate);
  expect_error(h.push(intraop_labels(), std::string("img-1"), true), ErrorCode::kConflict, "push");

  // Queued, then a restart: run again from the stored image alone.
  const std::string queued = parse_scan_push_reply(h.push_image(grid, std::string("img-2"))).scan_id;
  h.engine = test::FakeEngine{};
  h.open();
  ASSERT_TRUE(h.core->step(10ms));  // warm-up from the store
  EXPECT_FALSE(h.store->find(queued)->has_labels) << "has_labels survives the restart";
  ASSERT_TRUE(h.core->step(10ms));
  EXPECT_EQ(h.store->find(queued)->state, StoredScanState::done);
  EXPECT_FALSE(h.engine.last_scan_had_labels);
  ASSERT_TRUE(h.engine.last_scan_image.has_value());
  const ScanResultReply after = parse_scan_result_reply(
      h.call(make_scan_result_request("r", {queued, {ResultPart::kIntraopLabels}, {}})));
  ASSERT_NE(after.find("intraop_labels"), nullptr);
  EXPECT_EQ(after.find("intraop_labels")->bytes, r.find("intraop_labels")->bytes);
}

TEST(ServerCore, ShutdownRequestStopsTheEngineLoop) {
  Harness h;
  // Without CURVE a shutdown needs this (tests/server/test_security_settings.cpp).
  h.settings.security.allow_unauthenticated_shutdown = true;
  h.open();
  EXPECT_EQ(h.call(make_shutdown_request("bye")).type(), MessageType::kShutdownReply);
  EXPECT_TRUE(h.core->shutdown_requested());
  EXPECT_FALSE(h.core->step(10ms));
}

// ---- One test per row of the outputs table (protocol/result_outputs.h) -----
// The daemon serves, lists as pending, names as absent and repairs each part
// as its row says: whether it is deferred, which scans have it, what it is
// made again from after a crash.

namespace {

bool has_part(const ScanResultReply& r, ResultPart part) {
  if (part != ResultPart::kModels) return r.find(frame_name(part)) != nullptr;
  return std::any_of(r.frames.begin(), r.frames.end(),
                     [](const Frame& f) { return structure_of_model_frame(f.name).has_value(); });
}

const UnavailablePart* unavailable_part(const ScanResultReply& r, ResultPart part) {
  for (const auto& u : r.unavailable)
    if (part == ResultPart::kModels ? structure_of_model_frame(u.part).has_value() : u.part == frame_name(part))
      return &u;
  return nullptr;
}

std::vector<ResultOutput> rows(bool deferred_only) {
  std::vector<ResultOutput> out;
  for (const auto& row : kResultOutputs)
    if (row.deferred || !deferred_only) out.push_back(row);
  return out;
}

std::string row_name(const ::testing::TestParamInfo<ResultOutput>& info) { return std::string(info.param.wire); }

ScanResultReply pull(Harness& h, const std::string& scan_id, ResultPart part) {
  return parse_scan_result_reply(h.call(make_scan_result_request("row", {scan_id, {part}, {}})));
}

void deferred_part_lost_and_made_again(const ResultOutput& row, const ScanFacts& kind) {
  Harness h;
  h.load_preop();
  const std::string id = parse_scan_push_reply(push_kind(h, kind)).scan_id;
  ASSERT_TRUE(h.core->step(10ms));
  ASSERT_TRUE(has_part(pull(h, id, row.part), row.part));
  // Stopped before the part was stored: its file is not in the store.
  for (const auto& name : stored_file_names(row.part)) fs::remove(h.settings.store / "scans" / id / name);
  h.engine = test::FakeEngine{};
  h.open();
  const ScanResultReply before_repair = pull(h, id, row.part);
  for (int i = 0; i < 10 && h.core->step(10ms); ++i) {
  }
  EXPECT_TRUE(has_part(pull(h, id, row.part), row.part));
  if (row.remade_from) {
    // Re-encoded from the stored part at start-up, without registering again.
    EXPECT_TRUE(has_part(before_repair, row.part));
    EXPECT_EQ(h.engine.scans_run, 0);
  } else {
    const UnavailablePart* u = unavailable_part(before_repair, row.part);
    ASSERT_NE(u, nullptr);
    EXPECT_TRUE(u->pending) << "pulls answer pending until the repair has made it";
    EXPECT_EQ(h.engine.scans_run, 1) << "made again by registering the stored scan again";
  }
}

}  // namespace

class ResultRow : public ::testing::TestWithParam<ResultOutput> {};
class DeferredRow : public ::testing::TestWithParam<ResultOutput> {};

TEST_P(ResultRow, IsServedPendingOrAbsentAsItsRowSays) {
  const ResultOutput& row = GetParam();
  Harness h;
  h.load_preop();
  for (const ScanFacts& kind : kScanKinds) {
    SCOPED_TRACE(describe(kind));
    const std::string id = parse_scan_push_reply(push_kind(h, kind)).scan_id;
    std::optional<ScanResultReply> during;  // after scan.done, before the deferred parts
    h.engine.while_rendering_deferred = [&] { during = pull(h, id, row.part); };
    ASSERT_TRUE(h.core->step(10ms));
    ASSERT_TRUE(during.has_value());
    const ScanResultReply after = pull(h, id, row.part);
    const std::string_view absent = why_not_expected(row.part, kind);
    if (!absent.empty()) {  // this scan never has it
      for (const ScanResultReply* r : {static_cast<const ScanResultReply*>(&*during), &after}) {
        EXPECT_FALSE(has_part(*r, row.part));
        const UnavailablePart* u = unavailable_part(*r, row.part);
        ASSERT_NE(u, nullptr);
        EXPECT_FALSE(u->pending);
        EXPECT_EQ(u->reason, absent);
      }
      continue;
    }
    if (row.deferred) {
      const UnavailablePart* u = unavailable_part(*during, row.part);
      ASSERT_NE(u, nullptr) << "a deferred part was there before the deferred outputs ran";
      EXPECT_TRUE(u->pending);
    } else {
      EXPECT_TRUE(has_part(*during, row.part)) << "a part of the answer was not served at scan.done";
    }
    EXPECT_TRUE(has_part(after, row.part));
  }
}

TEST_P(DeferredRow, LostToACrashIsMadeAgainAtTheNextStart) {
  const ResultOutput& row = GetParam();
  for (const ScanFacts& kind : {ScanFacts{true, true}, ScanFacts{true, false}}) {
    SCOPED_TRACE(describe(kind));
    deferred_part_lost_and_made_again(row, kind);
  }
}

INSTANTIATE_TEST_SUITE_P(EveryRow, ResultRow, ::testing::ValuesIn(rows(false)), row_name);
INSTANTIATE_TEST_SUITE_P(EveryDeferredRow, DeferredRow, ::testing::ValuesIn(rows(true)), row_name);
