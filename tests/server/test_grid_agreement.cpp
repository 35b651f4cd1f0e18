// One grid-compatibility check: the daemon (a pushed scan's image against its
// labels, decoded by ServerCore) and `brainshift register` (the engine's
// validate_intraop_input, and the same Grid3::same_geometry before it) accept
// and refuse the same pairs of grids, at 1/100 of a voxel, for fine and
// coarse voxels, for shifts and for rotations. Labels on a part of the
// image's grid (a segmentation editor's box: image/label_placement.h) are
// placed on it, by both.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>

#include "core/errors.h"
#include "image/label_placement.h"
#include "image/nifti_io.h"
#include "label_table_file.h"
#include "core/label_table.h"
#include "pipeline/warm_state.h"
#include "protocol/media.h"
#include "server/case_store.h"
#include "server/server_core.h"
#include "test_support.h"

using namespace brainshift;
using namespace brainshift::protocol;
using namespace std::chrono_literals;

namespace {

// A ball of brain (1) with a ventricle core (2) on an axis-aligned grid of
// spacing_mm voxels; an oblique grid would hide which axis moved.
LabelImage labels_on(double spacing_mm) {
  LabelImage l = test::ball_labels(12);
  l.grid.world_from_voxel = Eigen::Matrix4d::Identity();
  l.grid.world_from_voxel.diagonal().head<3>().setConstant(spacing_mm);
  l.grid.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-60.0, 20.0, 5.0);
  return l;
}

// The labels' grid moved by `fraction` of the tolerance: a shift along y, or a
// rotation about z that moves the farthest corner by that much.
Grid3 moved(const Grid3& g, double fraction, bool rotate) {
  const double tol = Grid3::kSameGridVoxelFraction * g.spacing_mm().minCoeff();
  Grid3 m = g;
  if (!rotate) {
    m.world_from_voxel(1, 3) += fraction * tol;
    return m;
  }
  // Voxel (i,j,k) moves by angle * |(i,j)| * spacing about the k axis through voxel 0.
  const double reach_mm = std::hypot(g.dims[0] - 1, g.dims[1] - 1) * g.spacing_mm()[0];
  const Eigen::Matrix3d r = Eigen::AngleAxisd(fraction * tol / reach_mm, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  m.world_from_voxel.topLeftCorner<3, 3>() = r * g.world_from_voxel.topLeftCorner<3, 3>();
  return m;
}

ImageF image_on(const Grid3& g) {
  ImageF img(g);
  for (std::size_t i = 0; i < img.voxels.size(); ++i) img.voxels[i] = static_cast<float>(i % 13);
  return img;
}

bool register_accepts(const LabelImage& labels, const ImageF& image) {
  try {
    validate_intraop_input(IntraopInput{labels, image}, brainshift::config::default_label_table());
    return true;
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("different grids"), std::string::npos) << e.what();
    return false;
  }
}

struct Daemon {
  test::TempDir dir;
  server::ServerSettings settings;
  std::unique_ptr<server::CaseStore> store;
  test::FakeEngine engine;
  std::unique_ptr<server::ServerCore> core;

  Daemon() {
    settings.store = dir.path() / "store";
    settings.queue_depth = 16;
    settings.preop.kind = server::DefaultPreop::Kind::none;
    store = std::make_unique<server::CaseStore>(settings.store);
    core = std::make_unique<server::ServerCore>(settings, *store, engine, [](Message) {});
    core->start();
    PreopLoadRequest r;
    const LabelImage preop = test::ball_labels(10);
    r.t1 = media::nifti_frame("t1", scalar_image_to_bytes(test::ramp_image(preop.grid), VoxelType::float32, true));
    r.labels = media::nifti_frame("labels", label_image_to_bytes(preop, false));
    EXPECT_EQ(call(make_preop_load_request("p", r)).type(), MessageType::kPreopLoadReply);
    EXPECT_TRUE(core->step(10ms));
  }
  Message call(const Message& m) { return core->handle_wire(encode(m)); }

  // The preop's T1 and labels as an upload gives them; true when loaded.
  bool loads_preop(const ImageF& t1, const LabelImage& labels) {
    PreopLoadRequest r;
    r.t1 = media::nifti_frame("t1", scalar_image_to_bytes(t1, VoxelType::float32, true));
    r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, false));
    if (call(make_preop_load_request("p2", r)).type() != MessageType::kPreopLoadReply) return false;
    EXPECT_TRUE(core->step(10ms));
    return true;
  }

  bool accepts(const LabelImage& labels, const ImageF& image) {
    ScanPushRequest r;
    r.labels = media::nifti_frame("labels", label_image_to_bytes(labels, true));
    r.image = media::nifti_frame("image", scalar_image_to_bytes(image, VoxelType::float32, true));
    const Message reply = call(make_scan_push_request("push", r));
    if (reply.type() == MessageType::kScanPushReply) {
      EXPECT_TRUE(core->step(10ms));  // runs it, so the queue never fills
      return true;
    }
    EXPECT_EQ(reply.type(), MessageType::kError);
    const ErrorInfo e = parse_error_reply(reply);
    EXPECT_EQ(e.code, ErrorCode::kInvalidRequest) << e.message;
    EXPECT_NE(e.message.find("grid differs"), std::string::npos) << e.message;
    return false;
  }
};

TEST(GridAgreement, RegisterAndDaemonAcceptAndRefuseTheSameGrids) {
  Daemon daemon;
  for (double spacing_mm : {0.5, 1.0, 3.0}) {
    const LabelImage labels = labels_on(spacing_mm);
    for (bool rotate : {false, true}) {
      for (double fraction : {0.0, 0.5, 0.9, 1.5, 4.0}) {
        const ImageF image = image_on(moved(labels.grid, fraction, rotate));
        const bool expected = fraction <= 1.0;
        SCOPED_TRACE(testing::Message() << spacing_mm << " mm voxels, " << (rotate ? "rotated" : "shifted") << " by "
                                        << fraction << " x the tolerance");
        // Written and read back as NIfTI-1 (float sform), as both paths get them.
        const ImageF image_read = scalar_image_from_bytes(scalar_image_to_bytes(image, VoxelType::float32, false), "i", 1u << 26);
        const LabelImage labels_read = label_image_from_bytes(label_image_to_bytes(labels, false), "l", 1u << 26);
        EXPECT_EQ(labels_read.grid.same_geometry(image_read.grid), expected);
        EXPECT_EQ(register_accepts(labels_read, image_read), expected);
        EXPECT_EQ(daemon.accepts(labels, image), expected);
      }
    }
  }
}

TEST(GridAgreement, ToleranceIsAHundredthOfTheSmallerVoxel) {
  Grid3 a = labels_on(1.0).grid;
  Grid3 b = a;
  b.world_from_voxel(2, 2) = 0.5;  // other voxel size along z: a different grid anyway
  EXPECT_DOUBLE_EQ(a.same_grid_tolerance_mm(b), 0.005);
  EXPECT_FALSE(a.same_geometry(b));
  b = a;
  b.dims[0] += 1;
  EXPECT_FALSE(a.same_geometry(b)) << "dims must match exactly";
}

// An oblique grid of anisotropic voxels (a 3 mm axis) and labels on the
// voxels [lo, lo + dims) of it: a ball of brain with a ventricle core, on the
// image's own grid (whole) and on the box alone (part, as an editor stores it).
struct PartOfAGrid {
  Grid3 image_grid;
  LabelImage whole, part;
  PartOfAGrid(const std::array<int, 3>& lo, const std::array<int, 3>& dims) {
    image_grid.dims = {40, 44, 20};
    const Eigen::Matrix3d r = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 0.5).normalized()).toRotationMatrix();
    image_grid.world_from_voxel.topLeftCorner<3, 3>() = r * Eigen::Vector3d(-1.2, 1.2, 3.0).asDiagonal();
    image_grid.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(31.7, -88.3, 12.9);
    whole = LabelImage(image_grid, 0);
    part.grid.dims = dims;
    part.grid.world_from_voxel = image_grid.world_from_voxel;
    part.grid.world_from_voxel.col(3) = image_grid.world_from_voxel * Eigen::Vector4d(lo[0], lo[1], lo[2], 1);
    part.voxels.assign(part.grid.voxel_count(), 0);
    const Eigen::Vector3d centre_mm = image_grid.world_mm(20, 22, 10);
    for (int k = 0; k < dims[2]; ++k)
      for (int j = 0; j < dims[1]; ++j)
        for (int i = 0; i < dims[0]; ++i) {
          const double r_mm = (part.grid.world_mm(i, j, k) - centre_mm).norm();
          const std::uint16_t value = r_mm < 5 ? 2 : r_mm < 14 ? 1 : 0;
          part.at(i, j, k) = value;
          const int x = i + lo[0], y = j + lo[1], z = k + lo[2];
          if (value && x >= 0 && y >= 0 && z >= 0 && x < 40 && y < 44 && z < 20) whole.at(x, y, z) = value;
        }
  }
};

std::string refusal(const LabelImage& labels, const Grid3& image_grid) {
  try {
    labels_on_image_grid(labels, image_grid, "test labels");
  } catch (const InputError& e) {
    return e.what();
  }
  return "(placed)";
}

TEST(GridAgreement, LabelsOnAPartOfTheImagesGridArePlacedOnItExactly) {
  const PartOfAGrid box({6, 5, 3}, {28, 32, 14});
  ASSERT_GT(std::count(box.whole.voxels.begin(), box.whole.voxels.end(), 2), 0);
  const LabelImage placed = labels_on_image_grid(box.part, box.image_grid, "labels");
  EXPECT_TRUE(placed.grid.same_geometry(box.image_grid));
  EXPECT_EQ(placed.voxels, box.whole.voxels);
  // Written and read back (NIfTI-1's float sform), as both paths get them.
  const LabelImage read = label_image_from_bytes(label_image_to_bytes(box.part, false), "l", 1u << 26);
  EXPECT_EQ(labels_on_image_grid(read, box.image_grid, "labels").voxels, box.whole.voxels);
  // On the same grid: unchanged.
  EXPECT_EQ(labels_on_image_grid(box.whole, box.image_grid, "labels").voxels, box.whole.voxels);
  // A box reaching beyond the image with background there (an editor's
  // margin) is placed; labelled voxels beyond it are not dropped silently.
  const PartOfAGrid margin({-3, -2, -1}, {46, 50, 24});
  EXPECT_EQ(labels_on_image_grid(margin.part, margin.image_grid, "labels").voxels, margin.whole.voxels);
  PartOfAGrid cut({15, 5, 3}, {32, 32, 14});
  cut.part.at(31, 10, 5) = 1;  // image voxel x = 46 of 40
  EXPECT_NE(refusal(cut.part, cut.image_grid).find("labelled voxels lie beyond the image's grid"), std::string::npos)
      << refusal(cut.part, cut.image_grid);
  // Any other grid is refused: half a voxel off, another spacing, turned axes.
  LabelImage half = box.part;
  half.grid.world_from_voxel.col(3) += 0.5 * half.grid.world_from_voxel.col(1);
  LabelImage finer = box.part;
  finer.grid.world_from_voxel.col(2) *= 0.5;
  LabelImage turned = box.part;
  turned.grid.world_from_voxel.topLeftCorner<3, 3>() =
      Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitZ()).toRotationMatrix() * turned.grid.world_from_voxel.topLeftCorner<3, 3>();
  for (const LabelImage* other : {&half, &finer, &turned}) {
    const std::string why = refusal(*other, box.image_grid);
    EXPECT_NE(why.find("test labels: grid differs from the image's (28x32x14 against 40x44x20 voxels"), std::string::npos)
        << why;
    EXPECT_NE(why.find("not a part of the image's grid shifted by whole voxels"), std::string::npos) << why;
  }
}

TEST(GridAgreement, TheDaemonPlacesAPartsLabelsForAScanAndForAPreop) {
  Daemon daemon;
  const PartOfAGrid box({6, 5, 3}, {28, 32, 14});
  const ImageF image = image_on(box.image_grid);
  ASSERT_TRUE(daemon.accepts(box.part, image));
  ASSERT_TRUE(daemon.engine.last_labels.has_value());
  EXPECT_TRUE(daemon.engine.last_labels->grid.same_geometry(box.image_grid));
  EXPECT_EQ(daemon.engine.last_labels->voxels, box.whole.voxels);
  LabelImage half = box.part;
  half.grid.world_from_voxel.col(3) += 0.5 * half.grid.world_from_voxel.col(0);
  EXPECT_FALSE(daemon.accepts(half, image));
  // A preop upload: the engine gets the labels on the T1's grid.
  ASSERT_TRUE(daemon.loads_preop(image, box.part));
  EXPECT_EQ(daemon.engine.last_preop.labels.voxels, box.whole.voxels);
}

}  // namespace
