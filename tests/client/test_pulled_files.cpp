// `brainshift pull` writes register's file names: a plain-NIfTI frame bound
// for field.nii.gz must become a real .nii.gz holding the same image.
#include <gtest/gtest.h>
#include <zlib.h>

#include <filesystem>
#include <fstream>

#include "core/gzip.h"
#include "image/nifti_io.h"
#include "protocol/media.h"
#include "pulled_files.h"
#include "test_support.h"

using namespace brainshift;
namespace fs = std::filesystem;

TEST(PulledFiles, PlainNiftiFieldIsWrittenAsAValidNiiGzOfTheSameField) {
  const LabelImage labels = test::ball_labels(9);
  VectorImage3 field(labels.grid);
  for (std::size_t i = 0; i < field.vectors.size(); ++i)
    field.vectors[i] = Eigen::Vector3f(0.25f * static_cast<float>(i % 7), -1.5f, labels.voxels[i]);
  const protocol::Frame frame = protocol::media::nifti_frame("displacement", displacement_field_to_bytes(field, false));
  ASSERT_EQ(frame.media_type, protocol::media::kNifti);

  const cli::PulledFile f = cli::pulled_file_for(frame);
  EXPECT_EQ(f.name, "field.nii.gz");
  ASSERT_GE(f.bytes.size(), 2u);
  EXPECT_EQ(static_cast<unsigned char>(f.bytes[0]), 0x1f);
  EXPECT_EQ(static_cast<unsigned char>(f.bytes[1]), 0x8b);
  // Read back through the file reader, as a viewer would open the file.
  test::TempDir dir;
  const fs::path path = dir.path() / f.name;
  std::ofstream(path, std::ios::binary).write(f.bytes.data(), static_cast<std::streamsize>(f.bytes.size()));
  const VectorImage3 back = read_vector_image(path);
  ASSERT_TRUE(back.grid.same_geometry(field.grid));
  ASSERT_EQ(back.vectors.size(), field.vectors.size());
  for (std::size_t i = 0; i < field.vectors.size(); ++i) ASSERT_EQ(back.vectors[i], field.vectors[i]) << i;
}

TEST(PulledFiles, GzippedAndOtherFramesPassThroughUnchanged) {
  const LabelImage labels = test::ball_labels(6);
  const std::string gz = label_image_to_bytes(labels, true);
  const cli::PulledFile warped = cli::pulled_file_for(protocol::media::nifti_frame("warped_labels", gz));
  EXPECT_EQ(warped.name, "warped_labels.nii.gz");
  EXPECT_EQ(warped.bytes, gz);  // an older server's gzip is not gzipped twice
  const cli::PulledFile png = cli::pulled_file_for({"report", "image/png", test::FakeEngine::kReportPng});
  EXPECT_EQ(png.name, "report.png");
  EXPECT_EQ(png.bytes, test::FakeEngine::kReportPng);
  EXPECT_EQ(cli::pulled_file_for({"model.tumor", "application/x-vtk-polydata+xml", "<VTKFile"}).name,
            "models/tumor.vtp");
  EXPECT_EQ(cli::pulled_file_for({"mystery", "application/json", "{}"}).name, "");
}

TEST(PulledFiles, GzipRoundTripsThroughZlib) {
  std::string data(1 << 20, '\0');
  for (std::size_t i = 0; i < data.size(); ++i) data[i] = static_cast<char>((i * 2654435761u) >> 13);
  const std::string gz = gzip_bytes(data);
  z_stream z{};
  ASSERT_EQ(inflateInit2(&z, 15 + 16), Z_OK);
  std::string out(data.size() + 16, '\0');
  z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(gz.data()));
  z.avail_in = static_cast<uInt>(gz.size());
  z.next_out = reinterpret_cast<Bytef*>(out.data());
  z.avail_out = static_cast<uInt>(out.size());
  EXPECT_EQ(inflate(&z, Z_FINISH), Z_STREAM_END);
  out.resize(z.total_out);
  inflateEnd(&z);
  EXPECT_EQ(out, data);
  EXPECT_EQ(gzip_bytes("").substr(0, 2), "\x1f\x8b");
}
