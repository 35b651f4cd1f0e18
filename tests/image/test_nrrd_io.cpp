// NRRD in and out: round trips on an oblique left-handed grid, headers as
// Slicer and teem write them (RAS or LPS, raw or gzip, either byte order,
// detached .nhdr), Slicer segmentations mapped to the label table by name,
// and refusals. ITK reads what is written here in tests/field/itk.
#include <gtest/gtest.h>

#include <fstream>
#include <sstream>

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
  t.entries[0].role = LabelRole::parenchyma;
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

// A Slicer segmentation whose segments overlap, as Slicer stores it: one
// layer per set of non-overlapping segments along a leading list axis
// ("space directions: none ...", "kinds: list domain domain domain"), raw
// uint8, the layers of a voxel side by side.
std::string layered_segmentation(const Grid3& g, const std::vector<std::vector<std::uint8_t>>& layers,
                                 const std::string& segments) {
  const Eigen::Matrix4d lps = lps_world_from_ras_world_matrix(g.world_from_voxel);
  auto v = [](const Eigen::Vector3d& d) {
    std::ostringstream os;
    os.precision(17);
    os << '(' << d.x() << ',' << d.y() << ',' << d.z() << ')';
    return os.str();
  };
  std::ostringstream h;
  h << "NRRD0004\ntype: unsigned char\ndimension: 4\nspace: left-posterior-superior\nsizes: " << layers.size() << ' '
    << g.dims[0] << ' ' << g.dims[1] << ' ' << g.dims[2] << "\nspace directions: none " << v(lps.block<3, 1>(0, 0)) << ' '
    << v(lps.block<3, 1>(0, 1)) << ' ' << v(lps.block<3, 1>(0, 2))
    << "\nkinds: list domain domain domain\nencoding: raw\nspace origin: " << v(lps.block<3, 1>(0, 3)) << '\n'
    << segments << '\n';
  std::string data;
  for (std::size_t i = 0; i < g.voxel_count(); ++i)
    for (const auto& layer : layers) data.push_back(static_cast<char>(layer[i]));
  return h.str() + data;
}

TEST(NrrdIo, OverlappingSlicerSegmentsAreReadWithTheBrainContainingTheOthers) {
  test::TempDir dir;
  const Grid3 g = oblique_las();  // 7 x 5 x 4
  const std::size_t n = g.voxel_count();
  // Layer 0: the brain everywhere but voxel 0. Layer 1: the ventricles (1)
  // and the tumour (2) inside it, and the tract (3) on voxel 0 alone.
  std::vector<std::uint8_t> brain(n, 1), inner(n, 0);
  brain[0] = 0;
  inner[0] = 3;
  inner[10] = inner[11] = 1;
  inner[30] = 2;
  const std::string segments =
      "Segment0_Name:=Brain\nSegment0_LabelValue:=1\nSegment0_Layer:=0\n"
      "Segment1_Name:=ventricles\nSegment1_LabelValue:=1\nSegment1_Layer:=1\n"
      "Segment2_Name:=tumor\nSegment2_LabelValue:=2\nSegment2_Layer:=1\n"
      "Segment3_Name:=Corticospinal tract\nSegment3_LabelValue:=3\nSegment3_Layer:=1\n";
  std::ofstream(dir.path() / "layers.seg.nrrd", std::ios::binary) << layered_segmentation(g, {brain, inner}, segments);
  const LabelImage read = read_slicer_segmentation(dir.path() / "layers.seg.nrrd", table(), kMax);
  EXPECT_TRUE(read.grid.same_geometry(g));
  ASSERT_EQ(read.voxels.size(), n);
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint16_t expected = i == 0 ? 3 : (i == 10 || i == 11) ? 2 : i == 30 ? 4 : 1;
    EXPECT_EQ(read.voxels[i], expected) << i;
  }
  // The brain in the later layer: the same.
  std::ofstream(dir.path() / "swapped.seg.nrrd", std::ios::binary) << layered_segmentation(
      g, {inner, brain},
      "Segment0_Name:=Brain\nSegment0_LabelValue:=1\nSegment0_Layer:=1\n"
      "Segment1_Name:=ventricles\nSegment1_LabelValue:=1\nSegment1_Layer:=0\n"
      "Segment2_Name:=tumor\nSegment2_LabelValue:=2\nSegment2_Layer:=0\n"
      "Segment3_Name:=corticospinal-tract\nSegment3_LabelValue:=3\nSegment3_Layer:=0\n");
  EXPECT_EQ(read_slicer_segmentation(dir.path() / "swapped.seg.nrrd", table(), kMax).voxels, read.voxels);
  // Two structures other than the brain overlapping: refused, naming them.
  std::vector<std::uint8_t> tract(n, 0);
  tract[30] = tract[31] = 1;
  std::ofstream(dir.path() / "clash.seg.nrrd", std::ios::binary) << layered_segmentation(
      g, {brain, inner, tract}, segments + "Segment4_Name:=corticospinal_tract\nSegment4_LabelValue:=1\nSegment4_Layer:=2\n");
  try {
    read_slicer_segmentation(dir.path() / "clash.seg.nrrd", table(), kMax);
    FAIL() << "overlapping tumour and tract were accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("segments \"tumor\" and \"corticospinal_tract\" overlap in 1 voxels"),
              std::string::npos)
        << e.what();
  }
  // A segment in a layer the file does not have.
  std::ofstream(dir.path() / "nolayer.seg.nrrd", std::ios::binary)
      << layered_segmentation(g, {brain, inner}, segments + "Segment4_Name:=cst\nSegment4_LabelValue:=4\nSegment4_Layer:=2\n");
  try {
    read_slicer_segmentation(dir.path() / "nolayer.seg.nrrd", table(), kMax);
    FAIL() << "a segment in a missing layer was accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("Segment4_Layer 2 is not one of the file's 2 layers"), std::string::npos) << e.what();
  }
  // A plain label map with layers is still refused (it is no segmentation).
  std::ofstream(dir.path() / "layers.nrrd", std::ios::binary) << layered_segmentation(g, {brain, inner}, "");
  try {
    read_nrrd_labels(dir.path() / "layers.nrrd", kMax);
    FAIL() << "a layered label map was read as one";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("several layers or components"), std::string::npos) << e.what();
  }
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
