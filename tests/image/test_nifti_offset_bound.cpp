// A NIfTI header's vox_offset comes from the wire: a tiny file claiming data
// far away must fail as truncated without the reader allocating the claim
// (PROTOCOL.md 13.5). Peak resident memory is the observable.
#include <gtest/gtest.h>
#include <sys/resource.h>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "test_util.h"

namespace brainshift {
namespace {

long peak_rss_kib() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss;
}

TEST(NiftiOffsetBound, FarVoxOffsetInATinyFileIsTruncationNotAllocation) {
  ImageF image(Grid3{});
  image.grid.dims = {4, 4, 4};
  image.voxels.assign(64, 1.0f);
  std::string raw = scalar_image_to_bytes(image, VoxelType::float32, false);
  test::poke<float>(raw, test::offsets::vox_offset, 8.0e8f);  // 800 MB away; the file has 608 bytes
  const long before = peak_rss_kib();
  for (const std::string& bytes : {raw, test::gzip(raw)}) {
    try {
      scalar_image_from_bytes(bytes, "far_offset.nii", std::size_t{1} << 30);
      ADD_FAILURE() << "accepted";
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find("truncated"), std::string::npos) << e.what();
    }
  }
  const long grown_mib = (peak_rss_kib() - before) / 1024;
  EXPECT_LT(grown_mib, 100) << "the reader allocated about the claimed offset";
}

}  // namespace
}  // namespace brainshift
