// NRRD in and out: round trips on an oblique left-handed grid, headers as
// Slicer and teem write them (RAS or LPS, raw or gzip, either byte order,
// detached .nhdr), Slicer segmentations mapped to the label table by name,
// and refusals. ITK reads what is written here in tests/field/itk.
#include <gtest/gtest.h>

#include <fstream>

#include "core/errors.h"
#include "field/lps.h"
#include "image/label_placement.h"
#include "image/nrrd_io.h"
#include "temp_dir.h"

using namespace brainshift;
namespace fs = std::filesystem;

namespace {

constexpr std::size_t kMax = std::size_t{1} << 28;

Grid3 oblique_las() {
  Grid3 g;
  g.dims = {7, 5, 4};
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0.2, 0.4, 1).normalized()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = r * Eigen::Vector3d(-1.25, 0.9, 2.5).asDiagonal();
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(12.5, -40.25, 3.0);
  return g;
}

std::string read_text(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

std::string refusal(const fs::path& p) {
  try {
    read_nrrd_scalar(p, kMax);
  } catch (const InputError& e) {
    return e.what();
  }
  return "(read)";
}

LabelTable table() {
  LabelTable t;
  for (const auto& [value, name] : std::vector<std::pair<int, std::string>>{
           {1, "brain"}, {2, "ventricles"}, {3, "corticospinal_tract"}, {4, "tumor"}}) {
    LabelEntry e;
    e.value = static_cast<std::uint16_t>(value);
    e.name = name;
    t.entries.push_back(e);
  }
  t.entries[2].short_name = "cst";
  return t;
}

}  // namespace

TEST(NrrdIo, ScalarAndLabelsRoundTripInLps) {
  test::TempDir dir;
  ImageF image(oblique_las());
  for (std::size_t i = 0; i < image.voxels.size(); ++i) image.voxels[i] = 0.5f * static_cast<float>(i) - 3.25f;
  write_nrrd_scalar(dir.path() / "t1.nrrd", image);
  const ImageF back = read_nrrd_scalar(dir.path() / "t1.nrrd", kMax);
  EXPECT_LT(back.grid.max_voxel_offset_mm(image.grid), 1e-9);
  EXPECT_EQ(back.voxels, image.voxels);
  // The header says LPS, as Slicer writes: x and y of the origin negated.
  const std::string text = read_text(dir.path() / "t1.nrrd");
  EXPECT_NE(text.find("space: left-posterior-superior\n"), std::string::npos);
  EXPECT_NE(text.find("space origin: (-12.5,40.25,3)"), std::string::npos) << text.substr(0, 400);

  LabelImage labels(oblique_las());
  for (std::size_t i = 0; i < labels.voxels.size(); ++i) labels.voxels[i] = static_cast<std::uint16_t>(i % 5);
  write_nrrd_labels(dir.path() / "labels.nrrd", labels);
  const LabelImage lb = read_nrrd_labels(dir.path() / "labels.nrrd", kMax);
  EXPECT_TRUE(lb.grid.same_geometry(labels.grid));
  EXPECT_EQ(lb.voxels, labels.voxels);
}

TEST(NrrdIo, RasSpaceBigEndianAndDetachedData) {
  test::TempDir dir;
  // right-anterior-superior, big-endian int16, raw, data in a separate file.
  std::ofstream(dir.path() / "v.nhdr") << "NRRD0004\n# a comment\ntype: short\ndimension: 3\n"
                                          "space: right-anterior-superior\nsizes: 2 2 2\n"
                                          "space directions: (2,0,0) (0,3,0) (0,0,4)\nkinds: domain domain domain\n"
                                          "endian: big\nencoding: raw\nspace origin: (10,20,30)\ndata file: v.raw\n";
  std::string raw;
  for (int v = -4; v < 4; ++v) {
    const auto u = static_cast<std::uint16_t>(static_cast<std::int16_t>(v * 100));
    raw += static_cast<char>(u >> 8);
    raw += static_cast<char>(u & 0xff);
  }
  std::ofstream(dir.path() / "v.raw", std::ios::binary) << raw;
  const ImageF v = read_nrrd_scalar(dir.path() / "v.nhdr", kMax);
  EXPECT_EQ(v.voxels, (std::vector<float>{-400, -300, -200, -100, 0, 100, 200, 300}));
  EXPECT_EQ(v.grid.world_mm(1, 1, 1), Eigen::Vector3d(12, 23, 34));  // RAS, unconverted
}

TEST(NrrdIo, SlicerSegmentationMapsSegmentNamesToTheLabelTable) {
  test::TempDir dir;
  LabelImage stored(oblique_las());
  for (std::size_t i = 0; i < stored.voxels.size(); ++i) stored.voxels[i] = static_cast<std::uint16_t>(i % 3);
  write_nrrd_labels(dir.path() / "plain.nrrd", stored);
  // Slicer's keys on top of the header (segment 1 "Tumor" stored as 1, "CST" as 2).
  std::string text = read_text(dir.path() / "plain.nrrd");
  const std::string keys =
      "Segment0_Name:=Tumor\nSegment0_LabelValue:=1\nSegment0_Layer:=0\n"
      "Segment1_Name:=cst\nSegment1_LabelValue:=2\nSegment1_Layer:=0\n";
  text.insert(text.find("\n\n") + 1, keys);
  std::ofstream(dir.path() / "edit.seg.nrrd", std::ios::binary) << text;
  ASSERT_TRUE(is_slicer_segmentation_path(dir.path() / "edit.seg.nrrd"));
  const LabelImage mapped = read_slicer_segmentation(dir.path() / "edit.seg.nrrd", table(), kMax);
  for (std::size_t i = 0; i < stored.voxels.size(); ++i)
    EXPECT_EQ(mapped.voxels[i], stored.voxels[i] == 1 ? 4 : stored.voxels[i] == 2 ? 3 : 0) << i;

  std::string unknown = text;
  unknown.replace(unknown.find("Segment1_Name:=cst"), 18, "Segment1_Name:=skull");
  std::ofstream(dir.path() / "unknown.seg.nrrd", std::ios::binary) << unknown;
  try {
    read_slicer_segmentation(dir.path() / "unknown.seg.nrrd", table(), kMax);
    FAIL() << "an unknown segment was accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("\"skull\" is not in the label table (brain, ventricles"), std::string::npos)
        << e.what();
  }
}

// As 3D Slicer stores a segmentation: the box around its segments only, on
// the reference volume's spacing and axes, its origin moved to the box's
// first voxel (and the box's offset in Segmentation_ReferenceImageExtentOffset,
// which the standard fields make redundant). Read and placed on the
// reference volume's grid (image/label_placement.h), it is the segmentation
// drawn there, voxel for voxel.
TEST(NrrdIo, ASlicerSegmentationOfABoxIsPlacedOnItsVolumesGrid) {
  test::TempDir dir;
  Grid3 volume = oblique_las();
  volume.dims = {30, 26, 12};
  LabelImage drawn(volume, 0);
  for (int k = 4; k < 9; ++k)
    for (int j = 6; j < 20; ++j)
      for (int i = 11; i < 25; ++i) drawn.at(i, j, k) = (i + j) % 5 == 0 ? 2 : 1;
  const std::array<int, 3> lo = {10, 5, 3}, dims = {16, 16, 7};
  LabelImage box;
  box.grid.dims = dims;
  box.grid.world_from_voxel = volume.world_from_voxel;
  box.grid.world_from_voxel.col(3) = volume.world_from_voxel * Eigen::Vector4d(lo[0], lo[1], lo[2], 1);
  box.voxels.assign(box.grid.voxel_count(), 0);
  for (int k = 0; k < dims[2]; ++k)
    for (int j = 0; j < dims[1]; ++j)
      for (int i = 0; i < dims[0]; ++i) box.at(i, j, k) = drawn.at(i + lo[0], j + lo[1], k + lo[2]);
  write_nrrd_labels(dir.path() / "box.nrrd", box);
  std::string text = read_text(dir.path() / "box.nrrd");
  text.insert(text.find("\n\n") + 1,
              "Segmentation_ReferenceImageExtentOffset:=10 5 3\n"
              "Segment0_Name:=brain\nSegment0_LabelValue:=1\nSegment0_Layer:=0\n"
              "Segment1_Name:=ventricles\nSegment1_LabelValue:=2\nSegment1_Layer:=0\n");
  std::ofstream(dir.path() / "box.seg.nrrd", std::ios::binary) << text;
  const LabelImage read = read_slicer_segmentation(dir.path() / "box.seg.nrrd", table(), kMax);
  EXPECT_FALSE(read.grid.same_geometry(volume));
  const LabelImage placed = labels_on_image_grid(read, volume, "box.seg.nrrd");
  EXPECT_TRUE(placed.grid.same_geometry(volume));
  EXPECT_EQ(placed.voxels, drawn.voxels);
}

TEST(NrrdIo, WhatIsNotReadIsRefusedNamingTheField) {
  test::TempDir dir;
  const auto write = [&](const std::string& name, const std::string& header) {
    std::ofstream(dir.path() / name, std::ios::binary) << header << "\n" << std::string(64, '\0');
    return dir.path() / name;
  };
  const std::string base = "NRRD0004\ntype: float\ndimension: 3\nsizes: 2 2 2\nencoding: raw\nendian: little\n";
  EXPECT_NE(refusal(write("a.nrrd", base + "space: scanner-xyz\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"))
                .find("space \"scanner-xyz\""),
            std::string::npos);
  EXPECT_NE(refusal(write("b.nrrd", base + "space: LPS\n")).find("space directions"), std::string::npos);
  EXPECT_NE(refusal(write("f.nrrd", base + "space dimension: 3\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"))
                .find("no space field"),
            std::string::npos);
  EXPECT_NE(refusal(write("c.nrrd", "NRRD0004\ntype: float\ndimension: 4\nsizes: 3 2 2 2\nencoding: raw\n"
                                    "space: RAS\nspace directions: none (1,0,0) (0,1,0) (0,0,1)\n"))
                .find("non-spatial axis of 3"),
            std::string::npos);
  EXPECT_NE(refusal(write("d.nrrd", "P5 not nrrd")).find("not a NRRD"), std::string::npos);
  EXPECT_NE(refusal(write("e.nrrd", "NRRD0004\ntype: float\ndimension: 3\nsizes: 20 20 20\nencoding: raw\n"
                                    "space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"))
                .find("shorter"),
            std::string::npos);
}

TEST(NrrdIo, DisplacementIsASlicerResamplingGridTransformInLps) {
  test::TempDir dir;
  VectorImage3 field(oblique_las());
  for (std::size_t i = 0; i < field.vectors.size(); ++i) field.vectors[i] = Eigen::Vector3f(1.5f, -2.0f, 0.25f * i);
  write_nrrd_displacement(dir.path() / "field.nrrd", field);
  const std::string text = read_text(dir.path() / "field.nrrd");
  EXPECT_NE(text.find("displacement field type:=resampling\n"), std::string::npos);
  EXPECT_NE(text.find("kinds: vector domain domain domain\n"), std::string::npos);
  EXPECT_NE(text.find("sizes: 3 7 5 4\n"), std::string::npos);
}
