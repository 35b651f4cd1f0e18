// ITK's own transform reader on field.h5, checked against field.nii.gz.
//   itk_reads_field_h5 DIR   (DIR from write_itk_check_fields)
//
// field.nii.gz holds RAS vectors (NIfTI DISPVECT) on the intraop grid;
// field.h5 is an ITK DisplacementFieldTransform in LPS. At every grid point x
// the transform ITK builds from field.h5 must map F x to F (x + u(x)), with
// F = diag(-1, -1, 1) (engine/field/lps.h). field.nii.gz is read with the
// NIfTI reference library, not the engine's reader.
#include <gtest/gtest.h>
#include <nifti1_io.h>

#include <itkDisplacementFieldTransform.h>
#include <itkHDF5TransformIOFactory.h>
#include <itkTransformFactory.h>
#include <itkTransformFileReader.h>

#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>

#include "field/lps.h"

namespace {

std::filesystem::path g_dir;

struct NiftiField {
  int nx = 0, ny = 0, nz = 0;
  Eigen::Matrix4d ras_from_voxel = Eigen::Matrix4d::Identity();
  std::vector<float> data;  // x fastest, then y, z; the component slowest
  Eigen::Vector3d point(int i, int j, int k) const {
    return (ras_from_voxel * Eigen::Vector4d(i, j, k, 1)).head<3>();
  }
  Eigen::Vector3d vector(int i, int j, int k) const {
    const std::size_t n = static_cast<std::size_t>(nx) * ny * nz, v = i + nx * (j + static_cast<std::size_t>(ny) * k);
    return {data[v], data[v + n], data[v + 2 * n]};
  }
};

NiftiField read_nifti(const std::filesystem::path& path) {
  std::unique_ptr<nifti_image, decltype(&nifti_image_free)> nim(nifti_image_read(path.c_str(), 1), nifti_image_free);
  if (!nim) throw std::runtime_error(path.string() + ": niftilib cannot read it");
  if (nim->intent_code != NIFTI_INTENT_DISPVECT) throw std::runtime_error("intent is not DISPVECT (1006)");
  if (nim->datatype != NIFTI_TYPE_FLOAT32 || nim->nt != 1 || nim->nu != 3 || nim->sform_code <= 0)
    throw std::runtime_error("not a float32 3-vector field with an sform");
  NiftiField f;
  f.nx = nim->nx;
  f.ny = nim->ny;
  f.nz = nim->nz;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) f.ras_from_voxel(r, c) = nim->sto_xyz.m[r][c];  // float -> double, exact
  const float* values = static_cast<const float*>(nim->data);
  f.data.assign(values, values + nim->nvox);
  return f;
}

using DisplacementTransform = itk::DisplacementFieldTransform<double, 3>;

DisplacementTransform::Pointer read_with_itk(const std::filesystem::path& path) {
  auto reader = itk::TransformFileReaderTemplate<double>::New();
  reader->SetFileName(path.string());
  reader->Update();
  const auto* list = reader->GetTransformList();
  if (list->size() != 1) throw std::runtime_error(path.string() + ": expected one transform");
  DisplacementTransform::Pointer t = dynamic_cast<DisplacementTransform*>(list->front().GetPointer());
  if (!t) throw std::runtime_error(path.string() + ": ITK did not make a DisplacementFieldTransform_double_3_3");
  return t;
}

// Largest |ITK's TransformPoint(F x) - F (x + u(x))| over every grid point.
double worst_point_error_mm(const DisplacementTransform& t, const NiftiField& f) {
  double worst = 0;
  for (int k = 0; k < f.nz; ++k)
    for (int j = 0; j < f.ny; ++j)
      for (int i = 0; i < f.nx; ++i) {
        const Eigen::Vector3d x_lps = brainshift::ras_to_lps(f.point(i, j, k));
        const Eigen::Vector3d want = brainshift::ras_to_lps(f.point(i, j, k) + f.vector(i, j, k));
        DisplacementTransform::InputPointType p;
        for (int a = 0; a < 3; ++a) p[a] = x_lps[a];
        const auto q = t.TransformPoint(p);
        worst = std::max(worst, (Eigen::Vector3d(q[0], q[1], q[2]) - want).norm());
      }
  return worst;
}

class ItkReadsFieldH5 : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    itk::ObjectFactoryBase::RegisterFactory(itk::HDF5TransformIOFactory::New());
    itk::TransformFactory<DisplacementTransform>::RegisterTransform();
  }
  NiftiField nii = read_nifti(g_dir / "field.nii.gz");
};

// The grid ITK builds (its displacement image, LPS) is the NIfTI grid in LPS.
TEST_F(ItkReadsFieldH5, GridIsTheNiftiGridInLps) {
  const auto t = read_with_itk(g_dir / "field.h5");
  const auto* image = t->GetDisplacementField();
  const auto size = image->GetLargestPossibleRegion().GetSize();
  EXPECT_EQ(size[0], static_cast<unsigned>(nii.nx));
  EXPECT_EQ(size[1], static_cast<unsigned>(nii.ny));
  EXPECT_EQ(size[2], static_cast<unsigned>(nii.nz));
  const Eigen::Matrix4d lps_from_voxel = brainshift::lps_world_from_ras_world_matrix(nii.ras_from_voxel);
  for (int r = 0; r < 3; ++r) {
    EXPECT_NEAR(image->GetOrigin()[r], lps_from_voxel(r, 3), 1e-12);
    for (int c = 0; c < 3; ++c)
      EXPECT_NEAR(image->GetDirection()(r, c) * image->GetSpacing()[c], lps_from_voxel(r, c), 1e-12) << r << c;
  }
  // Oblique and left-handed, so a transposed or unflipped direction would show.
  EXPECT_LT((lps_from_voxel.topLeftCorner<3, 3>().determinant()), 0);
  EXPECT_GT(std::abs(lps_from_voxel(0, 1)), 0.1);
}

TEST_F(ItkReadsFieldH5, TransformPointMatchesTheNiftiFieldAtEveryGridPoint) {
  const double worst = worst_point_error_mm(*read_with_itk(g_dir / "field.h5"), nii);
  std::printf("field.h5 (double): worst |TransformPoint - (x + u)| = %.3g mm\n", worst);
  EXPECT_LT(worst, 1e-12);  // measured 8.9e-16 mm (ITK 5.2.1, Debian 12)
}

// The daemon's field.h5 has float parameters (like field.nii): ITK's double
// reader converts them, and the values are the NIfTI's float vectors exactly.
TEST_F(ItkReadsFieldH5, FloatFileReadsTheSameThroughTheDoubleReader) {
  const double worst = worst_point_error_mm(*read_with_itk(g_dir / "field_float.h5"), nii);
  std::printf("field_float.h5: worst |TransformPoint - (x + u)| = %.3g mm\n", worst);
  EXPECT_LT(worst, 1e-12);  // measured 8.9e-16 mm (ITK 5.2.1, Debian 12)
}

// The check can fail: the same field read without the LPS flip of the
// vectors misses by about twice their x and y components.
TEST_F(ItkReadsFieldH5, AnRasReadingWouldBeCaught) {
  const auto t = read_with_itk(g_dir / "field.h5");
  double worst = 0;
  for (int i = 0; i < nii.nx; ++i) {
    const Eigen::Vector3d x = nii.point(i, 3, 4), u = nii.vector(i, 3, 4);
    DisplacementTransform::InputPointType p;
    const Eigen::Vector3d x_lps = brainshift::ras_to_lps(x);
    for (int a = 0; a < 3; ++a) p[a] = x_lps[a];
    const auto q = t->TransformPoint(p);
    const Eigen::Vector3d unflipped = x_lps + u;  // RAS vector added to an LPS point
    worst = std::max(worst, (Eigen::Vector3d(q[0], q[1], q[2]) - unflipped).norm());
  }
  EXPECT_GT(worst, 0.5);
}

}  // namespace

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  if (argc != 2) {
    std::fprintf(stderr, "usage: itk_reads_field_h5 DIR\n");
    return 2;
  }
  g_dir = argv[1];
  return RUN_ALL_TESTS();
}
