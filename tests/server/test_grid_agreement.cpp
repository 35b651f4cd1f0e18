// One grid-compatibility check: the daemon (a pushed scan's image against its
// labels, decoded by ServerCore) and `brainshift register` (the engine's
// validate_intraop_input, and the same Grid3::same_geometry before it) accept
// and refuse the same pairs of grids, at 1/100 of a voxel, for fine and
// coarse voxels, for shifts and for rotations.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>

#include "core/errors.h"
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

}  // namespace
