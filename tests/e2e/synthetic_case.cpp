#include "synthetic_case.h"

#include "image/nifti_io.h"
#include "synthetic_head.h"
#include "image/resample.h"

namespace brainshift::e2e {
namespace {

using Head = test::SyntheticHead;

Grid3 grid(std::array<int, 3> dims, Eigen::Vector3d spacing, Eigen::Vector3d origin) {
  Grid3 g;
  g.dims = dims;
  g.world_from_voxel.topLeftCorner<3, 3>() = spacing.asDiagonal();
  g.world_from_voxel.block<3, 1>(0, 3) = origin;
  return g;
}

Head synthetic_head() {
  test::SyntheticHeadSpec spec;
  spec.dims = {70, 80, 62};
  spec.spacing_mm = 2;
  spec.origin_mm = {-69, -79, -61};
  spec.ventricle_semi_axes_mm = {8, 22, 10};
  spec.tumor_radius_mm = 7;
  return test::synthetic_head(spec);
}

}  // namespace

void write_synthetic_preop(const std::filesystem::path& dir) {
  const Head h = synthetic_head();
  write_scalar_image(dir / "preop_t1.nii.gz", h.t1);
  write_label_image(dir / "preop_labels.nii.gz", h.labels);
}

namespace {

void write_scan_on(const std::filesystem::path& dir, const std::string& prefix, const Eigen::Vector3d& shift_mm,
                   const Grid3& g, bool scanner_noise = false) {
  const Head h = synthetic_head();
  Eigen::Matrix4d preop_from_intraop = Eigen::Matrix4d::Identity();
  preop_from_intraop.block<3, 1>(0, 3) = -shift_mm;
  LabelImage labels = resample_nearest(h.labels, g, preop_from_intraop);
  for (auto& v : labels.voxels)
    if (v == 4) v = 1;  // intraop labels: 1 brain, 2 ventricles
  write_label_image(dir / (prefix + "_labels.nii.gz"), labels);
  const ImageF t1 = resample_linear(h.t1, g, preop_from_intraop);
  write_scalar_image(dir / (prefix + "_t1.nii.gz"), scanner_noise ? test::scanner_image(t1) : t1);
}

Grid3 imri_grid(double voxel_scale) {
  // iMRI-like: thick slices, its own field of view.
  auto n = [voxel_scale](int dim) { return static_cast<int>(dim / voxel_scale + 0.5); };
  return grid({n(96), n(110), n(44)}, Eigen::Vector3d(1.4, 1.4, 2.8) * voxel_scale, {-68, -77, -62});
}

}  // namespace

void write_synthetic_scan(const std::filesystem::path& dir, const std::string& prefix, const Eigen::Vector3d& shift_mm,
                          double voxel_scale) {
  write_scan_on(dir, prefix, shift_mm, imri_grid(voxel_scale));
}

void write_synthetic_noisy_scan(const std::filesystem::path& dir, const std::string& prefix,
                                const Eigen::Vector3d& shift_mm) {
  write_scan_on(dir, prefix, shift_mm, imri_grid(1.0), true);
}

void write_synthetic_oblique_las_scan(const std::filesystem::path& dir, const std::string& prefix,
                                      const Eigen::Vector3d& shift_mm) {
  Grid3 g;
  g.dims = {100, 112, 46};
  const Eigen::Matrix3d tilt = Eigen::AngleAxisd(0.21, Eigen::Vector3d(0.2, 0.3, 1).normalized()).toRotationMatrix();
  g.world_from_voxel.topLeftCorner<3, 3>() = tilt * Eigen::Vector3d(-1.4, 1.4, 2.8).asDiagonal();
  // Centred where the axis-aligned scan is.
  const Eigen::Vector3d centre(-1.5, -0.7, -1.8);
  const Eigen::Vector3d half_extent = 0.5 * Eigen::Vector3d(g.dims[0] - 1, g.dims[1] - 1, g.dims[2] - 1);
  g.world_from_voxel.block<3, 1>(0, 3) = centre - g.world_from_voxel.topLeftCorner<3, 3>() * half_extent;
  write_scan_on(dir, prefix, shift_mm, g);
}

}  // namespace brainshift::e2e
