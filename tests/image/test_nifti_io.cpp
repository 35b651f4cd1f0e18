// NIfTI round trips, every supported datatype, and every rejected defect.
#include <gtest/gtest.h>
#include <zlib.h>

#include <chrono>
#include <cmath>
#include <limits>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "temp_dir.h"
#include "test_util.h"

namespace brainshift {
namespace {

using test::offsets::data;
namespace off = test::offsets;

// Oblique, anisotropic, translated: rotation about an arbitrary axis times scale.
Eigen::Matrix4d oblique_affine(bool left_handed = false) {
  Eigen::Matrix4d a = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.4, Eigen::Vector3d(0.3, -0.5, 0.8).normalized()).toRotationMatrix();
  Eigen::Vector3d s(0.9, 1.1, 2.5);
  if (left_handed) s[0] = -s[0];
  a.topLeftCorner<3, 3>() = r * s.asDiagonal();
  a.topRightCorner<3, 1>() = Eigen::Vector3d(-80.5, 12.25, 30.0);
  return a;
}

Grid3 small_grid(bool left_handed = false) {
  Grid3 g;
  g.dims = {7, 5, 4};
  g.world_from_voxel = oblique_affine(left_handed);
  return g;
}

ImageF ramp_image(const Grid3& g, float scale, float offset) {
  ImageF img(g);
  for (std::size_t i = 0; i < img.voxels.size(); ++i) img.voxels[i] = offset + scale * static_cast<float>(i % 97);
  return img;
}

void expect_same_geometry(const Grid3& a, const Grid3& b) {
  EXPECT_EQ(a.dims, b.dims);
  EXPECT_LT((a.world_from_voxel - b.world_from_voxel).cwiseAbs().maxCoeff(), 1e-4)
      << a.world_from_voxel << "\nvs\n" << b.world_from_voxel;
}

// The exception's message must name the file (or stream) it is about.
template <class Fn>
void expect_input_error_naming(Fn&& fn, const std::string& name, const std::string& fragment) {
  try {
    fn();
    ADD_FAILURE() << "no InputError for " << name;
  } catch (const InputError& e) {
    const std::string msg = e.what();
    EXPECT_NE(msg.find(name), std::string::npos) << msg;
    EXPECT_NE(msg.find(fragment), std::string::npos) << "expected '" << fragment << "' in: " << msg;
  }
}

class NiftiFiles : public ::testing::Test {
 protected:
  test::TempDir tmp{"nifti"};
  const std::filesystem::path& dir = tmp.path();
};

TEST_F(NiftiFiles, ScalarFloat32RoundTripFileAndGzip) {
  const ImageF img = ramp_image(small_grid(), 0.37f, -5.f);
  for (const char* name : {"a.nii", "a.nii.gz"}) {
    write_scalar_image(dir / name, img);
    const ImageF back = read_scalar_image(dir / name);
    expect_same_geometry(img.grid, back.grid);
    EXPECT_EQ(img.voxels, back.voxels) << name;
  }
}

TEST_F(NiftiFiles, ScalarIntegerTypesExactForIntegerData) {
  const ImageF u8 = ramp_image(small_grid(), 2.f, 3.f);      // 3..195
  const ImageF i16 = ramp_image(small_grid(), -300.f, 50.f);  // negative, fits int16
  for (bool gz : {false, true}) {
    EXPECT_EQ(scalar_image_from_bytes(scalar_image_to_bytes(u8, VoxelType::uint8, gz), "u8", 1 << 20).voxels, u8.voxels);
    EXPECT_EQ(scalar_image_from_bytes(scalar_image_to_bytes(i16, VoxelType::int16, gz), "i16", 1 << 20).voxels,
              i16.voxels);
  }
}

TEST_F(NiftiFiles, ScalarUint8ScalesNonIntegerDataWithinOneStep) {
  const ImageF img = ramp_image(small_grid(), 0.013f, -0.4f);
  const ImageF back = scalar_image_from_bytes(scalar_image_to_bytes(img, VoxelType::uint8, false), "s", 1 << 20);
  const float step = (96 * 0.013f) / 255.f;
  for (std::size_t i = 0; i < img.voxels.size(); ++i) EXPECT_NEAR(back.voxels[i], img.voxels[i], 0.51f * step);
}

TEST_F(NiftiFiles, QformAgreesWithSformIncludingLeftHanded) {
  for (bool lh : {false, true}) {
    std::string bytes = scalar_image_to_bytes(ramp_image(small_grid(lh), 1.f, 0.f), VoxelType::float32, false);
    test::poke<std::int16_t>(bytes, off::sform_code, 0);  // force the reader onto the qform
    const ImageF back = scalar_image_from_bytes(bytes, "qform", 1 << 20);
    expect_same_geometry(small_grid(lh), back.grid);
  }
}

TEST_F(NiftiFiles, PixdimFallbackWhenNoSformNoQform) {
  std::string bytes = scalar_image_to_bytes(ramp_image(small_grid(), 1.f, 0.f), VoxelType::float32, false);
  test::poke<std::int16_t>(bytes, off::sform_code, 0);
  test::poke<std::int16_t>(bytes, off::qform_code, 0);
  const ImageF back = scalar_image_from_bytes(bytes, "analyze", 1 << 20);
  Eigen::Matrix4d expect = Eigen::Matrix4d::Identity();
  expect.diagonal().head<3>() = Eigen::Vector3d(0.9, 1.1, 2.5);
  EXPECT_LT((back.grid.world_from_voxel - expect).cwiseAbs().maxCoeff(), 1e-5);
}

TEST_F(NiftiFiles, LabelRoundTripUint8AndInt16) {
  LabelImage small(small_grid(), 0), big(small_grid(), 0);
  for (std::size_t i = 0; i < small.voxels.size(); ++i) {
    small.voxels[i] = static_cast<std::uint16_t>(i % 4);
    big.voxels[i] = static_cast<std::uint16_t>((i * 331) % 32768);
  }
  for (const char* name : {"l.nii", "l.nii.gz"}) {
    write_label_image(dir / name, small);
    const LabelImage back = read_label_image(dir / name);
    EXPECT_EQ(back.voxels, small.voxels);
    expect_same_geometry(small.grid, back.grid);
  }
  const std::string b = label_image_to_bytes(big, true);
  EXPECT_EQ(test::gunzip(b).substr(off::datatype, 2), std::string("\x04\x00", 2));  // int16
  EXPECT_EQ(label_image_from_bytes(b, "big", 1 << 20).voxels, big.voxels);
  big.voxels[3] = 40000;
  EXPECT_THROW(label_image_to_bytes(big, false), InputError);
}

TEST_F(NiftiFiles, LabelReaderRejectsNonIntegerValues) {
  ImageF img = ramp_image(small_grid(), 1.f, 0.f);
  img.voxels[5] = 2.5f;
  write_scalar_image(dir / "frac.nii", img);
  expect_input_error_naming([&] { read_label_image(dir / "frac.nii"); }, "frac.nii", "not integers");
  img.voxels[5] = -1.f;
  write_scalar_image(dir / "neg.nii", img);
  expect_input_error_naming([&] { read_label_image(dir / "neg.nii"); }, "neg.nii", "0..65535");
}

TEST_F(NiftiFiles, DisplacementFieldHeaderAndRoundTrip) {
  VectorImage3 field(small_grid());
  for (std::size_t i = 0; i < field.vectors.size(); ++i)
    field.vectors[i] = Eigen::Vector3f(0.1f * i, -0.2f * i, 3.f + i);
  const std::string raw = displacement_field_to_bytes(field, false);
  std::int16_t dim[8], intent;
  std::memcpy(dim, raw.data() + off::dim, sizeof(dim));
  std::memcpy(&intent, raw.data() + off::intent_code, 2);
  EXPECT_EQ(dim[0], 5);
  EXPECT_EQ(dim[4], 1);  // nt
  EXPECT_EQ(dim[5], 3);  // nu
  EXPECT_EQ(intent, 1006);
  // Planar: all x components, then all y, then all z.
  float first_y;
  std::memcpy(&first_y, raw.data() + data + 4 * field.vectors.size() + 4, 4);
  EXPECT_FLOAT_EQ(first_y, field.vectors[1].y());

  write_displacement_field(dir / "f.nii.gz", field);
  const VectorImage3 back = read_vector_image(dir / "f.nii.gz");
  expect_same_geometry(field.grid, back.grid);
  ASSERT_EQ(back.vectors.size(), field.vectors.size());
  for (std::size_t i = 0; i < field.vectors.size(); ++i) EXPECT_EQ(back.vectors[i], field.vectors[i]);
  // A 5-D field is not a scalar image.
  expect_input_error_naming([&] { read_scalar_image(dir / "f.nii.gz"); }, "f.nii.gz", "expected a 3-D image");
}

// One raw file per datatype, built from a float32 header by patching datatype and data.
std::string with_datatype(std::int16_t datatype, std::int16_t bitpix, const std::string& voxel_bytes) {
  ImageF img(Grid3{{2, 2, 2}, Eigen::Matrix4d::Identity()}, 0.f);
  std::string b = scalar_image_to_bytes(img, VoxelType::float32, false).substr(0, data);
  test::poke(b, off::datatype, datatype);
  test::poke(b, off::bitpix, bitpix);
  return b + voxel_bytes;
}

template <class T>
std::string typed(std::initializer_list<T> values) {
  std::string s;
  for (T v : values) s.append(reinterpret_cast<const char*>(&v), sizeof(T));
  return s;
}

TEST(NiftiDatatypes, EveryCommonTypeReadsAsFloat) {
  const std::vector<float> expect{0, 1, 2, 3, 4, 5, 6, 120};
  const std::vector<float> signed_expect{0, -1, 2, -3, 4, -5, 6, -120};
  struct Case { std::int16_t dt, bits; std::string bytes; const std::vector<float>* want; };
  const std::vector<Case> cases{
      {2, 8, typed<std::uint8_t>({0, 1, 2, 3, 4, 5, 6, 120}), &expect},
      {256, 8, typed<std::int8_t>({0, -1, 2, -3, 4, -5, 6, -120}), &signed_expect},
      {512, 16, typed<std::uint16_t>({0, 1, 2, 3, 4, 5, 6, 120}), &expect},
      {4, 16, typed<std::int16_t>({0, -1, 2, -3, 4, -5, 6, -120}), &signed_expect},
      {768, 32, typed<std::uint32_t>({0, 1, 2, 3, 4, 5, 6, 120}), &expect},
      {8, 32, typed<std::int32_t>({0, -1, 2, -3, 4, -5, 6, -120}), &signed_expect},
      {16, 32, typed<float>({0, -1, 2, -3, 4, -5, 6, -120}), &signed_expect},
      {64, 64, typed<double>({0, 1, 2, 3, 4, 5, 6, 120}), &expect},
  };
  for (const Case& c : cases) {
    const std::string b = with_datatype(c.dt, c.bits, c.bytes);
    EXPECT_EQ(scalar_image_from_bytes(b, "dt", 1 << 20).voxels, *c.want) << "datatype " << c.dt;
    EXPECT_EQ(scalar_image_from_bytes(test::gzip(b), "dt", 1 << 20).voxels, *c.want) << "gz datatype " << c.dt;
  }
}

TEST(NiftiDatatypes, SclSlopeAndInterAreApplied) {
  std::string b = with_datatype(2, 8, typed<std::uint8_t>({0, 1, 2, 3, 4, 5, 6, 7}));
  test::poke(b, off::scl_slope, 2.5f);
  test::poke(b, off::scl_inter, -3.f);
  const ImageF img = scalar_image_from_bytes(b, "slope", 1 << 20);
  for (int i = 0; i < 8; ++i) EXPECT_FLOAT_EQ(img.voxels[i], 2.5f * i - 3.f);
  // Labels stored with a slope of 2 decode to even integers.
  test::poke(b, off::scl_slope, 2.f);
  test::poke(b, off::scl_inter, 0.f);
  EXPECT_EQ(label_image_from_bytes(b, "lab", 1 << 20).voxels[7], 14);
}

TEST(NiftiDatatypes, BigEndianFileIsSwapped) {
  // Build a big-endian int16 file by swapping every header field we use.
  std::string b = with_datatype(4, 16, typed<std::int16_t>({0, 1, 2, 3, 4, 5, 6, 300}));
  ImageF little = scalar_image_from_bytes(b, "le", 1 << 20);
  auto swap_at = [&](std::size_t off, std::size_t size, std::size_t count) {
    for (std::size_t k = 0; k < count; ++k) std::reverse(b.begin() + off + k * size, b.begin() + off + (k + 1) * size);
  };
  swap_at(0, 4, 1);                // sizeof_hdr
  swap_at(off::dim, 2, 8);
  swap_at(68, 2, 4);               // intent_code, datatype, bitpix, slice_start
  swap_at(off::pixdim, 4, 11);     // pixdim[8], vox_offset, scl_slope, scl_inter
  swap_at(off::qform_code, 2, 2);
  swap_at(256, 4, 6 + 12);         // quaternion, offsets, srow_x/y/z
  swap_at(data, 2, 8);
  const ImageF big = scalar_image_from_bytes(b, "be", 1 << 20);
  EXPECT_EQ(big.voxels, little.voxels);
  expect_same_geometry(big.grid, little.grid);
}

// ------------------------------------------------------------ rejected input

class BadFiles : public NiftiFiles {
 protected:
  std::string good_raw() {
    return scalar_image_to_bytes(ramp_image(small_grid(), 1.f, 0.f), VoxelType::float32, false);
  }
  void expect_rejected(const std::string& file, const std::string& bytes, const std::string& fragment) {
    test::write_bytes(dir / file, bytes);
    expect_input_error_naming([&] { read_scalar_image(dir / file); }, file, fragment);
  }
};

TEST_F(BadFiles, MissingFile) {
  expect_input_error_naming([&] { read_scalar_image(dir / "nope.nii.gz"); }, "nope.nii.gz", "not found");
}

TEST_F(BadFiles, TruncatedRawAndGzip) {
  const std::string raw = good_raw();
  expect_rejected("trunc.nii", raw.substr(0, raw.size() - 10), "truncated");
  expect_rejected("trunc_header.nii", raw.substr(0, 200), "only 200 bytes");
  // Whole gzip stream of a truncated file, and a gzip stream cut in the middle.
  expect_rejected("trunc_data.nii.gz", test::gzip(raw.substr(0, raw.size() - 10)), "truncated");
  const std::string gz = test::gzip(raw);
  expect_rejected("cut.nii.gz", gz.substr(0, gz.size() * 9 / 10), "truncated");
  expect_rejected("cut_header.nii.gz", gz.substr(0, 40), "truncated");
}

TEST_F(BadFiles, HugeClaimInSmallFileIsTruncationNotAllocation) {
  std::string raw = good_raw();
  for (int d = 1; d <= 3; ++d) test::poke<std::int16_t>(raw, off::dim + 2 * d, 3000);  // 108 GB of float32
  expect_rejected("huge_claim.nii", raw, "truncated");
  expect_rejected("huge_claim.nii.gz", test::gzip(raw), "truncated");
}

TEST_F(BadFiles, GarbageAndBadMagic) {
  expect_rejected("garbage.nii", std::string(1000, 'x'), "not a NIfTI-1 or NIfTI-2 file");
  std::string raw = good_raw();
  raw[344] = 'X';
  expect_rejected("magic.nii", raw, "bad magic");
  expect_rejected("empty.nii.gz", "", "not a NIfTI file");
}

TEST_F(BadFiles, FourDimensionalWhereThreeExpected) {
  std::string raw = good_raw();
  const std::string voxels = raw.substr(data);
  test::poke<std::int16_t>(raw, off::dim, 4);
  test::poke<std::int16_t>(raw, off::dim + 8, 2);  // nt = 2
  expect_rejected("four_d.nii.gz", test::gzip(raw + voxels), "expected a 3-D image");
}

TEST_F(BadFiles, ZeroDimension) {
  std::string raw = good_raw();
  test::poke<std::int16_t>(raw, off::dim + 4, 0);  // ny = 0
  expect_rejected("zero_dim.nii", raw, "zero-sized");
}

TEST_F(BadFiles, NonFiniteOrSingularSform) {
  std::string raw = good_raw();
  test::poke(raw, off::srow_x + 4, std::numeric_limits<float>::quiet_NaN());
  expect_rejected("nan_sform.nii", raw, "NaN/Inf");
  raw = good_raw();
  for (int c = 0; c < 3; ++c) test::poke(raw, off::srow_x + 4 * c, 0.f);  // x row zero: rank 2
  expect_rejected("singular.nii", raw, "singular");
  raw = good_raw();
  test::poke(raw, off::srow_x, 0.f);  // first voxel axis has zero length
  test::poke(raw, off::srow_x + 16, 0.f);
  test::poke(raw, off::srow_x + 32, 0.f);
  expect_rejected("zero_axis.nii", raw, "voxel size");
}

TEST_F(BadFiles, ZeroOrAbsurdVoxelSize) {
  std::string raw = good_raw();
  test::poke<std::int16_t>(raw, off::sform_code, 0);
  test::poke<std::int16_t>(raw, off::qform_code, 0);
  test::poke(raw, off::pixdim + 4, 0.f);
  expect_rejected("zero_pixdim.nii", raw, "not positive");
  test::poke(raw, off::pixdim + 4, 250.f);
  expect_rejected("huge_pixdim.nii", raw, "outside [0.01, 100]");
  test::poke(raw, off::pixdim + 4, 0.001f);
  expect_rejected("tiny_pixdim.nii", raw, "outside [0.01, 100]");
}

TEST_F(BadFiles, NanVoxelsAreCounted) {
  std::string raw = good_raw();
  test::poke(raw, data + 4 * 3, std::numeric_limits<float>::quiet_NaN());
  test::poke(raw, data + 4 * 9, std::numeric_limits<float>::infinity());
  expect_rejected("nan_voxel.nii.gz", test::gzip(raw), "2 voxels are NaN or Inf");
}

TEST(GzipBomb, HeaderClaimingTooMuchIsRefusedBeforeAllocation) {
  ImageF tiny(Grid3{{2, 2, 2}, Eigen::Matrix4d::Identity()}, 0.f);
  std::string raw = scalar_image_to_bytes(tiny, VoxelType::float32, false);
  for (int d = 1; d <= 3; ++d) test::poke<std::int16_t>(raw, off::dim + 2 * d, 2000);  // 32 GB of float32
  const std::string gz = test::gzip(raw);
  ASSERT_LT(gz.size(), 1000u);
  const auto t0 = std::chrono::steady_clock::now();
  expect_input_error_naming([&] { scalar_image_from_bytes(gz, "bomb.nii.gz", 64u << 20); }, "bomb.nii.gz", "limit");
  // Refused from the header, before inflating: decompressing the claimed
  // 32 GB would take minutes, so even a loaded machine stays far below this.
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), 10.0);
}

TEST(GzipBomb, RealDataBeyondLimitIsRefused) {
  ImageF zeros(Grid3{{64, 64, 64}, Eigen::Matrix4d::Identity()}, 0.f);  // 1 MiB, compresses ~1000:1
  const std::string gz = scalar_image_to_bytes(zeros, VoxelType::float32, true);
  ASSERT_LT(gz.size(), 20000u);
  expect_input_error_naming([&] { scalar_image_from_bytes(gz, "zeros.nii.gz", 512u << 10); }, "zeros.nii.gz", "limit");
  EXPECT_NO_THROW(scalar_image_from_bytes(gz, "zeros.nii.gz", 2u << 20));
}

namespace {
// gzip with stored (level 0) deflate blocks: the voxel bytes appear verbatim in
// the stream, so one can be flipped and the stream still inflates; only the
// member's CRC-32 in the trailer tells.
std::string gzip_stored(const std::string& raw) {
  z_stream zs{};
  EXPECT_EQ(deflateInit2(&zs, 0, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY), Z_OK);
  std::string out(deflateBound(&zs, raw.size()), '\0');
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(raw.data()));
  zs.avail_in = static_cast<uInt>(raw.size());
  zs.next_out = reinterpret_cast<Bytef*>(out.data());
  zs.avail_out = static_cast<uInt>(out.size());
  EXPECT_EQ(deflate(&zs, Z_FINISH), Z_STREAM_END);
  out.resize(zs.total_out);
  deflateEnd(&zs);
  return out;
}
}  // namespace

TEST(GzipIntegrity, AFlippedByteThatStillInflatesIsCaughtByTheChecksum) {
  const LabelImage labels(Grid3{{8, 8, 8}, Eigen::Matrix4d::Identity()}, 1);
  const std::string raw = label_image_to_bytes(labels, false);
  std::string gz = gzip_stored(raw);
  EXPECT_EQ(label_image_from_bytes(gz, "ok.nii.gz", 1 << 20).voxels, labels.voxels);
  const std::size_t at = gz.find(std::string(64, '\x01'));  // a run of voxels, stored verbatim
  ASSERT_NE(at, std::string::npos);
  gz[at + 10] = '\x07';  // one voxel becomes label 7
  // Before the trailer was checked this read back with a wrong label, silently.
  expect_input_error_naming([&] { label_image_from_bytes(gz, "flipped.nii.gz", 1 << 20); }, "flipped.nii.gz",
                            "corrupt gzip");
}

TEST(GzipIntegrity, AStreamCutBeforeItsTrailerIsTruncated) {
  const LabelImage labels(Grid3{{8, 8, 8}, Eigen::Matrix4d::Identity()}, 1);
  const std::string gz = label_image_to_bytes(labels, true);
  // All voxel data are there; only the 8-byte trailer (CRC-32, length) is missing.
  expect_input_error_naming([&] { label_image_from_bytes(gz.substr(0, gz.size() - 8), "cut.nii.gz", 1 << 20); },
                            "cut.nii.gz", "truncated gzip");
}

TEST(GzipIntegrity, TrailingBytesAreBoundedAndNonGzipTrailersIgnored) {
  const LabelImage labels(Grid3{{8, 8, 8}, Eigen::Matrix4d::Identity()}, 1);
  const std::string raw = label_image_to_bytes(labels, false);
  // Padding after the last member is ignored, as gzip(1) does.
  EXPECT_EQ(label_image_from_bytes(test::gzip(raw) + std::string(16, '\0'), "padded.nii.gz", 1 << 20).voxels,
            labels.voxels);
  // A second member of 1 MiB of zeros after the image: inflated only within the limit.
  const std::string tail = test::gzip(std::string(1 << 20, '\0'));
  expect_input_error_naming([&] { label_image_from_bytes(test::gzip(raw) + tail, "tail.nii.gz", 64 << 10); },
                            "tail.nii.gz", "limit");
  EXPECT_NO_THROW(label_image_from_bytes(test::gzip(raw) + tail, "tail.nii.gz", 2 << 20));
}

TEST(NiftiWrite, RefusesNanAndBadGeometry) {
  ImageF img(small_grid(), 1.f);
  img.voxels[0] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_THROW(scalar_image_to_bytes(img, VoxelType::float32, false), InputError);
  ImageF flat(small_grid(), 1.f);
  flat.grid.world_from_voxel(2, 2) = 0.0;
  flat.grid.world_from_voxel.block<3, 1>(0, 2).setZero();
  EXPECT_THROW(scalar_image_to_bytes(flat, VoxelType::float32, false), InputError);
}

TEST(NiftiRealData, Colin27HeaderAndIntensities) {
  const std::filesystem::path ch2 = "/usr/share/mricron/templates/ch2.nii.gz";
  if (!std::filesystem::exists(ch2)) GTEST_SKIP() << "mricron templates not installed";
  const ImageF t1 = read_scalar_image(ch2);
  EXPECT_EQ(t1.grid.dims, (std::array<int, 3>{181, 217, 181}));
  EXPECT_NEAR(t1.grid.spacing_mm().minCoeff(), 1.0, 1e-6);
  // The MNI origin (0,0,0) is inside the brain, near the anterior commissure.
  const Eigen::Vector3d origin_vox = (t1.grid.voxel_from_world() * Eigen::Vector4d(0, 0, 0, 1)).head<3>();
  EXPECT_TRUE(t1.grid.contains(int(origin_vox[0]), int(origin_vox[1]), int(origin_vox[2])));
}

}  // namespace
}  // namespace brainshift
