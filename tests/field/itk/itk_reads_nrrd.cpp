// ITK's own NRRD reader (NrrdImageIO, as 3D Slicer's) on the NRRD files the
// engine writes (engine/image/nrrd_io.h), checked against the NIfTI files of
// the same images read with the NIfTI reference library:
//   itk_reads_nrrd DIR   (DIR from write_itk_check_fields)
// field.nrrd: every voxel at F x and its vector F u (F = diag(-1,-1,1), LPS),
// tagged "displacement field type" = "resampling" for Slicer; image.nrrd and
// labels.nrrd: the same voxels at the same (LPS) places.
#include <gtest/gtest.h>
#include <nifti1_io.h>

#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkMetaDataObject.h>
#include <itkNrrdImageIOFactory.h>
#include <itkVector.h>

#include <filesystem>
#include <memory>
#include <string>

#include "field/lps.h"

namespace {

std::filesystem::path g_dir;

struct Nifti {
  int n[3] = {0, 0, 0};
  int components = 1;
  Eigen::Matrix4d ras_from_voxel = Eigen::Matrix4d::Identity();
  std::vector<double> data;  // x fastest; components slowest
  std::size_t voxels() const { return static_cast<std::size_t>(n[0]) * n[1] * n[2]; }
  double at(std::size_t v, int c = 0) const { return data[v + c * voxels()]; }
};

Nifti read_nifti(const std::filesystem::path& path) {
  std::unique_ptr<nifti_image, decltype(&nifti_image_free)> nim(nifti_image_read(path.c_str(), 1), nifti_image_free);
  if (!nim) throw std::runtime_error(path.string() + ": niftilib cannot read it");
  Nifti f;
  f.n[0] = nim->nx;
  f.n[1] = nim->ny;
  f.n[2] = nim->nz;
  f.components = nim->nu > 0 ? nim->nu : 1;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) f.ras_from_voxel(r, c) = nim->sto_xyz.m[r][c];
  f.data.resize(nim->nvox);
  for (std::size_t i = 0; i < nim->nvox; ++i) {
    switch (nim->datatype) {
      case NIFTI_TYPE_FLOAT32: f.data[i] = static_cast<const float*>(nim->data)[i]; break;
      case NIFTI_TYPE_UINT16: f.data[i] = static_cast<const unsigned short*>(nim->data)[i]; break;
      case NIFTI_TYPE_INT16: f.data[i] = static_cast<const short*>(nim->data)[i]; break;
      case NIFTI_TYPE_UINT8: f.data[i] = static_cast<const unsigned char*>(nim->data)[i]; break;
      default: throw std::runtime_error(path.string() + ": datatype " + std::to_string(nim->datatype));
    }
  }
  return f;
}

template <class Image>
typename Image::Pointer read_with_itk(const std::filesystem::path& path) {
  auto reader = itk::ImageFileReader<Image>::New();
  reader->SetFileName(path.string());
  reader->Update();
  return reader->GetOutput();
}

// Largest distance between ITK's physical point of each voxel and F x of the NIfTI's.
template <class Image>
double worst_position_mm(const Image& image, const Nifti& nii) {
  double worst = 0;
  for (int k = 0; k < nii.n[2]; ++k)
    for (int j = 0; j < nii.n[1]; ++j)
      for (int i = 0; i < nii.n[0]; ++i) {
        typename Image::IndexType idx = {{i, j, k}};
        typename Image::PointType p;
        image.TransformIndexToPhysicalPoint(idx, p);
        const Eigen::Vector3d want = brainshift::ras_to_lps((nii.ras_from_voxel * Eigen::Vector4d(i, j, k, 1)).head<3>());
        worst = std::max(worst, (Eigen::Vector3d(p[0], p[1], p[2]) - want).norm());
      }
  return worst;
}

template <class Image>
void expect_same_scalars(const Image& image, const Nifti& nii) {
  const auto size = image.GetLargestPossibleRegion().GetSize();
  for (int a = 0; a < 3; ++a) ASSERT_EQ(static_cast<int>(size[a]), nii.n[a]);
  EXPECT_LT(worst_position_mm(image, nii), 1e-4);
  const auto* values = image.GetBufferPointer();
  double worst = 0;
  for (std::size_t v = 0; v < nii.voxels(); ++v) worst = std::max(worst, std::abs(double(values[v]) - nii.at(v)));
  EXPECT_EQ(worst, 0.0);
}

TEST(ItkReadsNrrd, FieldIsAnLpsResamplingGridTransform) {
  using Field = itk::Image<itk::Vector<float, 3>, 3>;
  const auto field = read_with_itk<Field>(g_dir / "field.nrrd");
  const Nifti nii = read_nifti(g_dir / "field.nii.gz");
  ASSERT_EQ(nii.components, 3);
  EXPECT_LT(worst_position_mm(*field, nii), 1e-4);
  double worst = 0;
  for (std::size_t v = 0; v < nii.voxels(); ++v) {
    const auto u = field->GetBufferPointer()[v];
    const Eigen::Vector3d want = brainshift::ras_to_lps(Eigen::Vector3d(nii.at(v, 0), nii.at(v, 1), nii.at(v, 2)));
    worst = std::max(worst, (Eigen::Vector3d(u[0], u[1], u[2]) - want).norm());
  }
  EXPECT_LT(worst, 1e-6) << "vectors are not the NIfTI's in LPS";
  std::string type;
  ASSERT_TRUE(itk::ExposeMetaData<std::string>(field->GetMetaDataDictionary(), "displacement field type", type));
  EXPECT_EQ(type, "resampling");
}

TEST(ItkReadsNrrd, ImageAndLabelsAreTheNiftiVoxelsInLps) {
  expect_same_scalars(*read_with_itk<itk::Image<float, 3>>(g_dir / "image.nrrd"), read_nifti(g_dir / "image.nii.gz"));
  expect_same_scalars(*read_with_itk<itk::Image<unsigned short, 3>>(g_dir / "labels.nrrd"),
                      read_nifti(g_dir / "labels.nii.gz"));
}

}  // namespace

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  if (argc != 2) {
    std::fprintf(stderr, "usage: itk_reads_nrrd DIR\n");
    return 2;
  }
  itk::NrrdImageIOFactory::RegisterOneFactory();
  g_dir = argv[1];
  return RUN_ALL_TESTS();
}
