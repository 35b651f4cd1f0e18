// Frame content checks by magic number.
#include <gtest/gtest.h>

#include <cstdint>
#include <cstring>
#include <utility>

#include "protocol/media.h"
#include "test_util.h"

namespace bp = brainshift::protocol;
namespace media = brainshift::protocol::media;

TEST(Media, NiftiFrameChoosesMediaTypeFromTheBytes) {
  EXPECT_EQ(media::nifti_frame("a", bp::testing::fake_gzip(10)).media_type, media::kNiftiGz);
  EXPECT_EQ(media::nifti_frame("a", bp::testing::fake_nifti(1, 1, 1)).media_type, media::kNifti);
}

TEST(Media, AcceptsWellFormedContent) {
  EXPECT_NO_THROW(media::check_content(media::nifti_frame("a", bp::testing::fake_nifti(2, 2, 2))));
  EXPECT_NO_THROW(media::check_content(media::nifti_frame("a", bp::testing::fake_gzip(10))));
  EXPECT_NO_THROW(media::check_content({"m", std::string(media::kVtp), bp::testing::fake_vtp()}));
  EXPECT_NO_THROW(media::check_content({"h", std::string(media::kItkH5), bp::testing::fake_h5()}));
  EXPECT_NO_THROW(media::check_content(media::json_frame("j", R"({"a":1})")));
}

TEST(Media, RefusesContentThatContradictsTheMediaType) {
  std::string nifti = bp::testing::fake_nifti(2, 2, 2);
  std::string bad_magic = nifti;
  bad_magic[345] = '2';  // "n+2" at NIfTI-1's magic offset is neither NIfTI-1 nor NIfTI-2
  EXPECT_THROW(media::check_content({"a", std::string(media::kNifti), bad_magic}), bp::ProtocolError);
  EXPECT_THROW(media::check_content({"a", std::string(media::kNifti), nifti.substr(0, 300)}),
               bp::ProtocolError);
  EXPECT_THROW(media::check_content({"a", std::string(media::kNiftiGz), nifti}), bp::ProtocolError);
  EXPECT_THROW(media::check_content({"h", std::string(media::kItkH5), "not hdf5"}), bp::ProtocolError);
  EXPECT_THROW(media::check_content({"m", std::string(media::kVtp), "<VTKFile type=\"UnstructuredGrid\">"}),
               bp::ProtocolError);
  EXPECT_THROW(media::check_content(media::json_frame("j", "{")), bp::ProtocolError);
  EXPECT_THROW(media::check_content({"x", "image/png", "\x89PNG"}), bp::ProtocolError);
}

TEST(Media, AcceptsANifti2HeaderAndRefusesAMismatchedOne) {
  std::string nifti2(544 + 8, '\0');
  const std::int32_t sizeof_hdr = 540;
  std::memcpy(nifti2.data(), &sizeof_hdr, 4);
  std::memcpy(nifti2.data() + 4, "n+2\0\r\n\032\n", 8);
  EXPECT_EQ(media::nifti_frame("a", nifti2).media_type, media::kNifti);
  EXPECT_NO_THROW(media::check_content(media::nifti_frame("a", nifti2)));
  std::string swapped = nifti2;
  std::swap(swapped[0], swapped[3]);
  std::swap(swapped[1], swapped[2]);
  EXPECT_NO_THROW(media::check_content({"a", std::string(media::kNifti), swapped}));
  std::string n1_magic = nifti2;
  std::memcpy(n1_magic.data() + 4, "n+1\0", 4);  // NIfTI-2 size with a NIfTI-1 magic
  EXPECT_THROW(media::check_content({"a", std::string(media::kNifti), n1_magic}), bp::ProtocolError);
  EXPECT_THROW(media::check_content({"a", std::string(media::kNifti), nifti2.substr(0, 400)}), bp::ProtocolError);
}

TEST(Media, AcceptsABigEndianNiftiHeader) {
  std::string nifti = bp::testing::fake_nifti(1, 1, 1);
  std::swap(nifti[0], nifti[3]);
  std::swap(nifti[1], nifti[2]);
  EXPECT_NO_THROW(media::check_content({"a", std::string(media::kNifti), nifti}));
}
