// The OpenIGTLink gateway's queries, as 3D Slicer's OpenIGTLink Remote sends
// them (GET_IMGMETA, GET_LBMETA, GET_IMAGE, GET_POLYDATA, STT_/STP_): first
// with the project's receiver (every reply unpacked with its CRC), then with
// OpenIGTLink's own example clients, built from Debian's
// openigtlink-examples sources (tests/server/CMakeLists.txt).
#include <gtest/gtest.h>

#include <chrono>
#include <optional>
#include <cstring>
#include <regex>
#include <thread>

#include <nlohmann/json.hpp>

#include "e2e/process.h"
#include "igtl_receiver.h"
#include "igtl_test_store.h"
#include "server/igtl_gateway.h"

using namespace brainshift;
using namespace brainshift::server;
using namespace std::chrono_literals;
using test::IgtlReceived;
using test::IgtlReceiver;

namespace {

OpenIgtlinkSettings queries_only() {
  OpenIgtlinkSettings s = test::any_port();
  s.push = false;
  return s;
}

IgtlReceived ask(IgtlReceiver& r, const std::string& type, const std::string& device) {
  r.send_query(type, device);
  auto m = r.next();
  if (!m) throw std::runtime_error("no reply to " + type + " " + device);
  return *m;
}

std::string status_scan(const IgtlReceived& m) {
  return nlohmann::json::parse(m.status()->GetStatusString()).at("scan_id");
}

std::size_t count(const std::string& text, const std::string& what) {
  std::size_t n = 0;
  for (auto at = text.find(what); at != std::string::npos; at = text.find(what, at + what.size())) ++n;
  return n;
}

// Runs one of OpenIGTLink's example clients against the port; its output
// (it prints to stderr, and exits 0 whatever happens).
std::string run_example(const std::string& binary, int port, const std::filesystem::path& dir) {
  const auto r = e2e::run({binary, "127.0.0.1", std::to_string(port)}, dir, 60);
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  return r.out + r.err;
}

}  // namespace

TEST(IgtlQueries, ListsTheStoredScansAndReturnsEachByName) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string older = test::store_result(store, 1.0f, 12);
  const std::string newer = test::store_result(store, 2.0f, 14);
  IgtlGateway gateway(queries_only(), store, config::default_label_table());
  IgtlReceiver slicer(gateway.port(), 10s);

  // IMGMETA: the warped image and the field of each scan, newest first.
  const IgtlReceived meta = ask(slicer, "GET_IMGMETA", "");
  ASSERT_EQ(meta.type, "IMGMETA");
  ASSERT_NE(meta.image_meta(), nullptr);
  std::vector<std::string> devices;
  for (int i = 0; i < meta.image_meta()->GetNumberOfImageMetaElement(); ++i) {
    ::igtl::ImageMetaElement::Pointer e;
    meta.image_meta()->GetImageMetaElement(i, e);
    devices.push_back(e->GetDeviceName());
    igtlUint16 size[3];
    e->GetSize(size);
    const int n = devices.back().rfind(newer, 0) == 0 ? 14 : 12;
    EXPECT_EQ(size[0], n);
    EXPECT_EQ(size[2], n);
    EXPECT_EQ(e->GetScalarType(), ::igtl::ImageMessage::TYPE_FLOAT32);
  }
  EXPECT_EQ(devices, (std::vector<std::string>{newer + ".image", newer + ".field", older + ".image", older + ".field"}));

  // LBMETA: each label map's structures, by the label table's names and colours.
  const IgtlReceived lb = ask(slicer, "GET_LBMETA", "Client");
  ASSERT_EQ(lb.type, "LBMETA");
  EXPECT_EQ(lb.device, "Client");  // a reply is named as its query
  const LabelTable table = config::default_label_table();
  ASSERT_EQ(lb.label_meta()->GetNumberOfLabelMetaElement(), static_cast<int>(2 * table.entries.size()));
  ::igtl::LabelMetaElement::Pointer first;
  lb.label_meta()->GetLabelMetaElement(0, first);
  EXPECT_EQ(std::string(first->GetDeviceName()), newer + ".labels");
  EXPECT_EQ(std::string(first->GetOwner()), newer + ".image");
  EXPECT_EQ(first->GetLabel(), table.entries[0].value);
  EXPECT_EQ(std::string(first->GetName()), newer + " " + table.entries[0].name);
  igtlUint8 rgba[4];
  first->GetRGBA(rgba);
  EXPECT_EQ(rgba[0], table.entries[0].colour[0]);
  EXPECT_EQ(rgba[2], table.entries[0].colour[2]);

  // GET_IMAGE by a listed name: the older scan's field, exactly as stored.
  const IgtlReceived field = ask(slicer, "GET_IMAGE", older + ".field");
  ASSERT_NE(field.image(), nullptr);
  EXPECT_EQ(field.device, older + ".field");
  EXPECT_EQ(field.image()->GetNumComponents(), 3);
  const auto* v = static_cast<const float*>(field.image()->GetScalarPointer());
  EXPECT_EQ(v[0], 1.0f);
  EXPECT_EQ(v[1], -1.0f);
  EXPECT_EQ(v[2], 2.0f);
  EXPECT_LT((test::igtl_world_from_voxel(*field.image()) - test::small_grid(12).world_from_voxel).cwiseAbs().maxCoeff(),
            1e-4);
  // The pushed names are the newest scan's.
  const IgtlReceived labels = ask(slicer, "GET_IMAGE", "bs.warped_labels");
  ASSERT_NE(labels.image(), nullptr);
  EXPECT_EQ(labels.image()->GetScalarType(), ::igtl::ImageMessage::TYPE_UINT16);
  int dims[3];
  labels.image()->GetDimensions(dims);
  EXPECT_EQ(dims[0], 14);
  const LabelImage stored = test::ball_labels(14);
  EXPECT_EQ(std::memcmp(labels.image()->GetScalarPointer(), stored.voxels.data(), stored.voxels.size() * 2), 0);
  // Unnamed: any data, named for what it is.
  EXPECT_EQ(ask(slicer, "GET_IMAGE", "").device, newer + ".image");

  // GET_POLYDATA by the pushed model name.
  const IgtlReceived tumor = ask(slicer, "GET_POLYDATA", "bs.model.tumor");
  ASSERT_NE(tumor.polydata(), nullptr);
  igtlFloat32 p[3];
  tumor.polydata()->GetPoints()->GetPoint(1, p);
  EXPECT_FLOAT_EQ(p[0], 10.0f);
  EXPECT_FLOAT_EQ(p[2], -2.0f);  // triangle_fan(-value) of the newer scan
  EXPECT_EQ(tumor.polydata()->GetPolygons()->GetNumberOfCells(), 2u);
  EXPECT_EQ(status_scan(ask(slicer, "GET_STATUS", "")), newer);

  // What is not there: a null body of the type asked, named as asked.
  for (const auto& [type, device] : std::vector<std::pair<std::string, std::string>>{
           {"GET_IMAGE", "scan-999999.image"}, {"GET_IMAGE", "scan-000001.nonsense"},
           {"GET_POLYDATA", "bs.model.nothing"}, {"GET_TRANS", "Tracker"}, {"GET_IMAGE", "bs." + std::string(17, 'x')}}) {
    const IgtlReceived r = ask(slicer, type, device);
    EXPECT_EQ(r.type, type.substr(4));
    EXPECT_EQ(r.device, device.substr(0, 20));
    EXPECT_EQ(r.body_size, 0u) << type << " " << device;
  }
  // A name that is not the gateway's (the client's own label) asks for any data.
  const IgtlReceived any = ask(slicer, "GET_POLYDATA", "Client");
  ASSERT_NE(any.polydata(), nullptr);
  EXPECT_EQ(any.device, "Client");
  EXPECT_EQ(any.polydata()->GetPoints()->GetNumberOfPoints(), 4u);
  EXPECT_EQ(gateway.info().messages_dropped, 0u);
}

// The engine's segmentation of an image pushed alone travels as a label
// IMAGE (uint16, the table's values) named bs.intraop_labels, after the warped
// labels; it is listed in LBMETA and answered by GET_IMAGE.
TEST(IgtlQueries, TheSegmentationOfAnImageAloneIsALabelImage) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string labelled = test::store_result(store, 1.0f, 12);
  const std::string image_only = test::store_image_only_result(store, 2.0f, 14);
  IgtlGateway gateway(test::any_port(), store, config::default_label_table());
  IgtlReceiver slicer(gateway.port(), 10s);
  const auto pushed = slicer.next_result();
  std::vector<std::string> devices;
  for (const auto& m : pushed) devices.push_back(m.device);
  EXPECT_EQ(devices, (std::vector<std::string>{"bs.field", "bs.warped_image", "bs.warped_labels", "bs.intraop_labels",
                                               "bs.model.brain", "bs.model.tumor", "bs.status"}));
  const LabelImage stored = test::ball_labels(14);
  const IgtlReceived& seg = pushed[3];
  ASSERT_NE(seg.image(), nullptr);
  EXPECT_EQ(seg.image()->GetScalarType(), ::igtl::ImageMessage::TYPE_UINT16);
  EXPECT_EQ(std::memcmp(seg.image()->GetScalarPointer(), stored.voxels.data(), stored.voxels.size() * 2), 0);
  EXPECT_LT((test::igtl_world_from_voxel(*seg.image()) - stored.grid.world_from_voxel).cwiseAbs().maxCoeff(), 1e-4);

  for (const std::string& name : {std::string("bs.intraop_labels"), image_only + ".seg"}) {
    const IgtlReceived asked = ask(slicer, "GET_IMAGE", name);
    ASSERT_NE(asked.image(), nullptr) << name;
    EXPECT_EQ(asked.device, name);
    EXPECT_EQ(std::memcmp(asked.image()->GetScalarPointer(), stored.voxels.data(), stored.voxels.size() * 2), 0);
  }
  // A scan pushed with labels has no segmentation of the engine's.
  EXPECT_EQ(ask(slicer, "GET_IMAGE", labelled + ".seg").body_size, 0u);

  const LabelTable table = config::default_label_table();
  const IgtlReceived lb = ask(slicer, "GET_LBMETA", "");
  std::size_t segmentation_entries = 0;
  for (int i = 0; i < lb.label_meta()->GetNumberOfLabelMetaElement(); ++i) {
    ::igtl::LabelMetaElement::Pointer e;
    lb.label_meta()->GetLabelMetaElement(i, e);
    if (std::string(e->GetDeviceName()) != image_only + ".seg") continue;
    EXPECT_EQ(std::string(e->GetOwner()), image_only + ".image");
    ++segmentation_entries;
  }
  EXPECT_EQ(segmentation_entries, table.entries.size());
  EXPECT_EQ(lb.label_meta()->GetNumberOfLabelMetaElement(), static_cast<int>(3 * table.entries.size()));
}

TEST(IgtlQueries, SttAndStpStartAndStopThePushes) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string first = test::store_result(store, 1.0f);
  IgtlGateway gateway(queries_only(), store, config::default_label_table());
  IgtlReceiver r(gateway.port(), 3s);
  // push = false: nothing arrives unasked.
  gateway.publish(first);
  EXPECT_FALSE(r.next().has_value());

  const IgtlReceived started = ask(r, "STT_IMAGE", "bs.field");
  EXPECT_EQ(started.type, "RTS_IMAGE");
  EXPECT_EQ(started.device, "bs.field");
  EXPECT_EQ(started.raw_body, std::string(1, '\0'));
  EXPECT_EQ(status_scan(r.next_result().back()), first);  // the current result at once
  const std::string second = test::store_result(store, 2.0f);
  gateway.publish(second);
  EXPECT_EQ(status_scan(r.next_result().back()), second);

  EXPECT_EQ(ask(r, "STP_POLYDATA", "").type, "RTS_POLYDATA");
  gateway.publish(test::store_result(store, 3.0f));
  EXPECT_FALSE(r.next().has_value()) << "pushed after STP_";
  // Still answered while stopped; a type the gateway does not stream is refused.
  EXPECT_EQ(ask(r, "GET_STATUS", "").type, "STATUS");
  EXPECT_EQ(ask(r, "STT_TDATA", "Tracker").raw_body, std::string(1, '\1'));
}

TEST(IgtlQueries, OpenIgtlinkExampleClientsGetTheirAnswers) {
  test::TempDir dir;
  CaseStore store(dir.path() / "store");
  const std::string scan = test::store_result(store, 1.5f);
  {
    IgtlGateway gateway(queries_only(), store, config::default_label_table());
    const std::string meta = run_example(IGTL_IMAGE_META_CLIENT, gateway.port(), dir.path());
    EXPECT_EQ(count(meta, "Receiving IMGMETA data type."), 10u) << meta;
    EXPECT_EQ(count(meta, " DeviceName : " + scan + ".image"), 10u) << meta;
    EXPECT_EQ(count(meta, "Invalid response"), 0u) << meta;
    const std::string lb = run_example(IGTL_LABEL_META_CLIENT, gateway.port(), dir.path());
    EXPECT_EQ(count(lb, "Receiving LBMETA data type."), 10u) << lb;
    EXPECT_EQ(count(lb, " DeviceName : " + scan + ".labels"), 10 * config::default_label_table().entries.size()) << lb;
    EXPECT_EQ(count(lb, " Owner      : " + scan + ".image"), 10 * config::default_label_table().entries.size()) << lb;
    // PolyDataClient asks for "Client", not a name of the gateway's: any
    // available model, the newest scan's first (brain).
    const std::string poly = run_example(IGTL_POLYDATA_CLIENT, gateway.port(), dir.path());
    EXPECT_EQ(count(poly, "Receiving POLYDATA data type."), 10u) << poly;
    EXPECT_EQ(count(poly, "point[3] = (-10, 0, 1.5)"), 10u) << poly;
    // The same client asking by the pushed name, as Slicer does, gets that model.
    const std::string named = run_example(IGTL_POLYDATA_CLIENT_NAMED, gateway.port(), dir.path());
    EXPECT_EQ(count(named, "Receiving POLYDATA data type."), 10u) << named;
    EXPECT_EQ(count(named, "point[3] = (-10, 0, 1.5)"), 10u) << named;
    EXPECT_EQ(count(named, "cell[1] = (0, 0, 2, 3)"), 10u) << named;
    EXPECT_EQ(count(named, "Invalid response"), 0u) << named;
  }
  // ReceiveClient decodes every pushed IMAGE and STATUS with its CRC check;
  // it runs until the server closes.
  std::optional<IgtlGateway> pushing;
  pushing.emplace(test::any_port(), store, config::default_label_table());
  e2e::Process receive({IGTL_RECEIVE_CLIENT, "127.0.0.1", std::to_string(pushing->port())}, dir.path() / "rc.out",
                       dir.path() / "rc.err");
  const auto until = std::chrono::steady_clock::now() + 20s;
  while (pushing->info().messages_sent < 6 && std::chrono::steady_clock::now() < until)
    std::this_thread::sleep_for(10ms);
  ASSERT_EQ(pushing->info().messages_sent, 6u);
  std::this_thread::sleep_for(200ms);  // sent is counted when written: let the client read
  pushing.reset();  // closes the connection: ReceiveClient exits
  ASSERT_TRUE(receive.wait(20).has_value());
  const std::string out = e2e::read_file(dir.path() / "rc.err");
  for (const char* device : {"bs.field", "bs.warped_image", "bs.warped_labels"})
    EXPECT_EQ(count(out, std::string("Device Name           : ") + device + "\n"), 1u) << device << "\n" << out;
  EXPECT_EQ(count(out, "Receiving : POLYDATA"), 2u) << out;  // skipped, as it has no POLYDATA reader
  EXPECT_EQ(count(out, " Error Name: nonrigid"), 1u) << out;
  EXPECT_NE(out.find("\"scan_id\":\"" + scan + "\""), std::string::npos) << out;
}
