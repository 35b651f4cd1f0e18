// Writes the fixture of the ITK reader check (itk/): one smooth, non-trivial
// pull-back field on an oblique, left-handed (LAS-like) grid, as register
// writes it: field.nii.gz (NIfTI DISPVECT, RAS vectors), field.h5 (double, as
// `brainshift register`) and field_float.h5 (float, as the daemon); and the
// NRRD files of a field, an image and labels with their NIfTI twins.
//   write_itk_check_fields OUT_DIR
#include <cmath>
#include <filesystem>
#include <iostream>

#include "field/itk_transform_io.h"
#include "image/nifti_io.h"
#include "image/nrrd_io.h"

int main(int argc, char** argv) {
  namespace bs = brainshift;
  if (argc != 2) {
    std::cerr << "usage: write_itk_check_fields OUT_DIR\n";
    return 2;
  }
  try {
    const std::filesystem::path out = argv[1];
    std::filesystem::create_directories(out);
    bs::Grid3 g;
    g.dims = {23, 19, 11};
    const Eigen::Matrix3d rotation =
        Eigen::AngleAxisd(0.35, Eigen::Vector3d(0.3, -0.5, 0.8).normalized()).toRotationMatrix();
    // First axis towards the patient's left (x flipped): a LAS-like grid.
    g.world_from_voxel.topLeftCorner<3, 3>() = rotation * Eigen::Vector3d(-1.2, 0.9, 2.1).asDiagonal();
    g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(14.5, -22.25, 7.0);
    // NIfTI-1 stores the sform as float32 while field.h5 keeps doubles: an
    // affine made of float values gives both files the same grid, so the
    // check compares the vectors and frames, not float rounding (~1e-6 mm).
    g.world_from_voxel = g.world_from_voxel.cast<float>().cast<double>();
    bs::VectorImage3 field(g);
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          const Eigen::Vector3d x = g.world_mm(i, j, k);
          // Every component non-zero and varying: a sign or axis mix-up shows.
          field.vectors[g.index(i, j, k)] = Eigen::Vector3f(static_cast<float>(2.0 * std::sin(0.11 * x.y()) + 0.7),
                                                            static_cast<float>(-1.5 * std::cos(0.07 * x.z()) + 0.3 * x.x() / 10),
                                                            static_cast<float>(0.9 + 0.02 * x.x() - 0.03 * x.y()));
        }
    bs::write_displacement_field(out / "field.nii.gz", field);
    bs::write_itk_displacement_transform(out / "field.h5", field);
    bs::ItkTransformWriteOptions single;
    single.single_precision = true;
    bs::write_itk_displacement_transform(out / "field_float.h5", field, single);
    // The NRRD files 3D Slicer would load, beside their NIfTI twins.
    bs::write_nrrd_displacement(out / "field.nrrd", field);
    bs::ImageF image(g);
    bs::LabelImage labels(g);
    for (std::size_t v = 0; v < image.voxels.size(); ++v) {
      image.voxels[v] = 0.75f * static_cast<float>(v % 97) - 20.5f;
      labels.voxels[v] = static_cast<std::uint16_t>((v * 7) % 5);
    }
    bs::write_scalar_image(out / "image.nii.gz", image);
    bs::write_nrrd_scalar(out / "image.nrrd", image);
    bs::write_label_image(out / "labels.nii.gz", labels);
    bs::write_nrrd_labels(out / "labels.nrrd", labels);
  } catch (const std::exception& e) {
    std::cerr << "write_itk_check_fields: " << e.what() << '\n';
    return 1;
  }
  return 0;
}
