#include <gtest/gtest.h>

#include <unistd.h>

#include <fstream>

#include "server/case_store.h"
#include "test_support.h"

using namespace brainshift;
using namespace brainshift::server;
using brainshift::test::TempDir;
namespace fs = std::filesystem;

namespace {

PreopRecord sample_preop(const std::string& id) {
  PreopRecord p;
  p.preop_id = id;
  p.source = "upload";
  p.labels = test::ball_labels(9);
  p.t1 = test::ramp_image(p.labels.grid);
  p.label_table_json = R"({"v":1,"structures":{"brain":[1]}})";
  return p;
}

PushedScan sample_input(char fill, bool image) {
  PushedScan in;
  in.labels_bytes = std::string(1000, fill);
  (*in.labels_bytes)[10] = '\0';  // binary-safe
  if (image) in.image_bytes = std::string(333, static_cast<char>(fill + 1));
  return in;
}

}  // namespace

TEST(CaseStore, PreopRoundTripKeepsVoxelsAndGeometry) {
  TempDir dir;
  CaseStore store(dir.path());
  EXPECT_FALSE(store.has_preop());
  const PreopRecord p = sample_preop("preop-a");
  store.save_preop(p);
  EXPECT_TRUE(store.has_preop());
  CaseStore reopened(dir.path());
  const PreopRecord q = reopened.load_preop();
  EXPECT_EQ(q.preop_id, "preop-a");
  EXPECT_EQ(q.source, "upload");
  EXPECT_EQ(q.label_table_json, p.label_table_json);
  EXPECT_EQ(q.t1.grid.dims, p.t1.grid.dims);
  EXPECT_EQ(q.t1.grid.world_from_voxel, p.t1.grid.world_from_voxel);
  EXPECT_EQ(q.t1.voxels, p.t1.voxels);
  EXPECT_EQ(q.labels.voxels, p.labels.voxels);
}

TEST(CaseStore, MeshRoundTripIsExactAndTiedToItsPreop) {
  TempDir dir;
  CaseStore store(dir.path());
  store.save_preop(sample_preop("preop-a"));
  const TetMesh m = test::two_tet_mesh();
  store.save_mesh("preop-a", m);
  const auto back = store.load_mesh("preop-a");
  ASSERT_TRUE(back);
  EXPECT_EQ(back->nodes_mm, m.nodes_mm);
  EXPECT_EQ(back->tets, m.tets);
  EXPECT_EQ(back->tet_labels, m.tet_labels);
  ASSERT_EQ(back->boundary_faces.size(), 2u);
  EXPECT_EQ(back->boundary_faces[1].nodes, m.boundary_faces[1].nodes);
  EXPECT_EQ(back->boundary_faces[1].neighbour_label, 2);
  EXPECT_FALSE(store.load_mesh("preop-b"));
  // A new preop drops the old preop's mesh: it must never be reused.
  store.save_preop(sample_preop("preop-b"));
  EXPECT_FALSE(fs::exists(dir.path() / "mesh.h5"));
}

TEST(CaseStore, ScansAndResultsSurviveReopen) {
  TempDir dir;
  std::string id1, id2;
  const std::map<std::string, std::string> files = {
      {"field.nii.gz", std::string("\x1f\x8b\0binary", 9)}, {"models/brain.vtp", "<VTKFile/>"}, {"empty.json", ""}};
  {
    CaseStore store(dir.path());
    const PushedScan a = sample_input('a', true);
    id1 = store.add_scan(a, std::string("client-1"), content_digest(a), "preop-a").scan_id;
    id2 = store.add_scan(sample_input('b', false), std::nullopt, "d2", "preop-a").scan_id;
    EXPECT_NE(id1, id2);
    store.save_result(id1, files, {});
    store.save_failure(id2, "scan_failed", "solver diverged", "solve");
    EXPECT_EQ(*store.read_result_file(id1, "field.nii.gz"), files.at("field.nii.gz"));
  }
  CaseStore store(dir.path());
  const auto r1 = store.find(id1);
  ASSERT_TRUE(r1);
  EXPECT_EQ(r1->state, StoredScanState::done);
  EXPECT_EQ(r1->client_scan_id.value(), "client-1");
  EXPECT_TRUE(r1->has_image);
  EXPECT_EQ(r1->result.kind, protocol::ResultKind::nonrigid);
  EXPECT_TRUE(r1->finished_at.has_value());
  EXPECT_EQ(store.find_by_client_id("client-1")->scan_id, id1);
  for (const auto& [name, bytes] : files) EXPECT_EQ(store.read_result_file(id1, name).value(), bytes) << name;
  EXPECT_FALSE(store.read_result_file(id1, "nope"));
  EXPECT_EQ(store.result_file_names(id1).size(), 3u);
  const PushedScan in = store.load_scan_input(id1);
  EXPECT_EQ(in.labels_bytes, sample_input('a', true).labels_bytes);
  EXPECT_EQ(in.image_bytes.value(), sample_input('a', true).image_bytes.value());
  const auto r2 = store.find(id2);
  EXPECT_EQ(r2->state, StoredScanState::failed);
  EXPECT_EQ(r2->error_stage, "solve");
  EXPECT_EQ(r2->error_message, "solver diverged");
  EXPECT_FALSE(store.load_scan_input(id2).image_bytes);
  // New ids continue after the stored ones.
  const auto id3 = store.add_scan(sample_input('c', false), std::nullopt, "d3", "preop-a").scan_id;
  EXPECT_GT(id3, id2);
  const auto listed = store.list_newest_first(2);
  ASSERT_EQ(listed.size(), 2u);
  EXPECT_EQ(listed[0].scan_id, id3);
  EXPECT_EQ(listed[1].scan_id, id2);
  const auto queued = store.queued_oldest_first();
  ASSERT_EQ(queued.size(), 1u);
  EXPECT_EQ(queued[0].scan_id, id3);
}

// An image pushed alone (PROTOCOL.md 5.3, revision 4): stored without
// labels, read back as such, and its digest apart from any labelled scan's.
TEST(CaseStore, AnImageAloneIsStoredAndReadBackWithoutLabels) {
  TempDir dir;
  PushedScan image_only;
  image_only.image_bytes = std::string(500, 'i');
  PushedScan empty_labels = image_only;
  empty_labels.labels_bytes = std::string();
  EXPECT_NE(content_digest(image_only), content_digest(empty_labels));
  EXPECT_EQ(content_digest(image_only).substr(16), "-0-500");
  std::string id;
  {
    CaseStore store(dir.path());
    id = store.add_scan(image_only, std::string("img"), content_digest(image_only), "preop-a").scan_id;
    EXPECT_FALSE(store.find(id)->has_labels);
    EXPECT_THROW(store.add_scan(PushedScan{}, std::nullopt, "d", "preop-a"), std::invalid_argument);
  }
  CaseStore store(dir.path());
  const auto r = store.find(id);
  ASSERT_TRUE(r);
  EXPECT_FALSE(r->has_labels);
  EXPECT_TRUE(r->has_image);
  EXPECT_EQ(r->digest, content_digest(image_only));
  const PushedScan back = store.load_scan_input(id);
  EXPECT_FALSE(back.labels_bytes.has_value());
  EXPECT_EQ(back.image_bytes.value(), image_only.image_bytes.value());
  const PushedScan labelled = sample_input('a', true);
  const std::string labelled_id = store.add_scan(labelled, std::nullopt, content_digest(labelled), "preop-a").scan_id;
  EXPECT_TRUE(store.find(labelled_id)->has_labels);
}

TEST(CaseStore, HalfWrittenFilesAreIgnoredAndRemovedOnOpen) {
  TempDir dir;
  std::string id;
  {
    CaseStore store(dir.path());
    id = store.add_scan(sample_input('a', false), std::nullopt, "d", "p").scan_id;
  }
  // What a kill -9 in the middle of writes leaves behind.
  fs::create_directories(dir.path() / "scans" / ".tmp-scan-000099");
  std::ofstream(dir.path() / "scans" / ".tmp-scan-000099" / "scan.h5") << "half an HDF5 file";
  std::ofstream(dir.path() / "scans" / id / "result.h5.tmp") << "half a result";
  std::ofstream(dir.path() / "preop.h5.tmp") << "half a preop";
  // And a damaged scan directory (not produced by us, but must not stop the store).
  fs::create_directories(dir.path() / "scans" / "scan-000050");
  std::ofstream(dir.path() / "scans" / "scan-000050" / "scan.h5") << "garbage";

  CaseStore store(dir.path());
  EXPECT_FALSE(fs::exists(dir.path() / "scans" / ".tmp-scan-000099"));
  EXPECT_FALSE(fs::exists(dir.path() / "scans" / id / "result.h5.tmp"));
  EXPECT_FALSE(fs::exists(dir.path() / "preop.h5.tmp"));
  EXPECT_FALSE(store.has_preop());
  EXPECT_FALSE(store.find("scan-000099"));
  EXPECT_FALSE(store.find("scan-000050"));
  const auto r = store.find(id);
  ASSERT_TRUE(r);
  EXPECT_EQ(r->state, StoredScanState::queued);  // its result never completed: run again
  EXPECT_EQ(store.queued_oldest_first().size(), 1u);
}

TEST(CaseStore, ThePushsLabelsUseIsStoredDigestedAndReadBack) {
  TempDir dir;
  PushedScan exact = sample_input('a', true);
  exact.labels_use = "exact";
  // A push that did not say digests as before the field existed.
  EXPECT_NE(content_digest(exact), content_digest(sample_input('a', true)));
  std::string id;
  {
    CaseStore store(dir.path());
    id = store.add_scan(exact, std::nullopt, content_digest(exact), "preop-a").scan_id;
  }
  CaseStore store(dir.path());  // a restart processes the scan as it was pushed
  EXPECT_EQ(store.find(id)->labels_use, std::optional<std::string>("exact"));
  EXPECT_EQ(store.load_scan_input(id).labels_use, std::optional<std::string>("exact"));
  const PushedScan plain = sample_input('b', true);
  const std::string plain_id = store.add_scan(plain, std::nullopt, content_digest(plain), "preop-a").scan_id;
  EXPECT_FALSE(store.load_scan_input(plain_id).labels_use.has_value());
}

TEST(CaseStore, DigestSeparatesContent) {
  EXPECT_EQ(content_digest(sample_input('a', true)), content_digest(sample_input('a', true)));
  EXPECT_NE(content_digest(sample_input('a', true)), content_digest(sample_input('a', false)));
  EXPECT_NE(content_digest(sample_input('a', false)), content_digest(sample_input('b', false)));
}

TEST(CaseStore, UnusableDirectoryIsReported) {
  TempDir dir;
  std::ofstream(dir.path() / "file") << "x";
  EXPECT_THROW(CaseStore(dir.path() / "file" / "store"), std::runtime_error);
  if (::geteuid() != 0) {  // root ignores permissions
    fs::create_directories(dir.path() / "ro");
    fs::permissions(dir.path() / "ro", fs::perms::owner_read | fs::perms::owner_exec);
    EXPECT_THROW(CaseStore(dir.path() / "ro"), std::runtime_error);
  }
}

TEST(CaseStore, UnknownScanResultIsRefused) {
  TempDir dir;
  CaseStore store(dir.path());
  EXPECT_THROW(store.save_result("scan-404", {}, {}), std::invalid_argument);
  EXPECT_FALSE(store.read_result_file("scan-404", "field.nii.gz"));
}

TEST(CaseStore, FileAddedAfterTheResultIsServedAndSurvivesReopen) {
  TempDir dir;
  std::string id, queued_id;
  const std::string png("\x89PNG\r\n\x1a\nrest of a picture", 25);
  {
    CaseStore store(dir.path());
    id = store.add_scan(sample_input('a', true), std::nullopt, "d", "p").scan_id;
    queued_id = store.add_scan(sample_input('b', true), std::nullopt, "d2", "p").scan_id;
    // Only a done scan takes extra files, and only plain names of its own.
    EXPECT_THROW(store.add_result_file(queued_id, "report.png", png), std::invalid_argument);
    store.save_result(id, {{"metrics.json", "{}"}}, {});
    EXPECT_THROW(store.add_result_file(id, "result.h5", png), std::invalid_argument);
    EXPECT_THROW(store.add_result_file(id, "../escape.png", png), std::invalid_argument);
    EXPECT_THROW(store.add_result_file(id, "x.tmp", png), std::invalid_argument);
    store.add_result_file(id, "report.png", png);
    EXPECT_EQ(store.read_result_file(id, "report.png").value(), png);
    EXPECT_EQ(store.read_result_file(id, "metrics.json").value(), "{}");
  }
  // A write interrupted by a crash leaves only a .tmp, which is removed.
  std::ofstream(dir.path() / "scans" / id / "other.png.tmp") << "half";
  CaseStore store(dir.path());
  EXPECT_FALSE(fs::exists(dir.path() / "scans" / id / "other.png.tmp"));
  EXPECT_EQ(store.read_result_file(id, "report.png").value(), png);
  EXPECT_EQ(store.read_result_file(id, "metrics.json").value(), "{}");
  EXPECT_EQ(store.result_file_names(id).size(), 2u);
}
