#pragma once
// A small synthetic head for the daemon tests: an ellipsoidal brain (label 1)
// with two ventricles (2) and a tumour (4), and intraop scans of it moved by a
// known translation on an anisotropic iMRI-like grid.
#include <filesystem>

#include <Eigen/Dense>

namespace brainshift::e2e {

// Writes preop_t1.nii.gz and preop_labels.nii.gz into dir.
void write_synthetic_preop(const std::filesystem::path& dir);
// Writes <prefix>_labels.nii.gz and <prefix>_t1.nii.gz: the preop moved by shift_mm.
// voxel_scale > 1 makes the intraop voxels that much larger (fewer of them,
// same field of view): smaller results, for the soak test.
void write_synthetic_scan(const std::filesystem::path& dir, const std::string& prefix, const Eigen::Vector3d& shift_mm,
                          double voxel_scale = 1.0);
// The same scan as write_synthetic_scan with a scanner's noise and bias on
// the image (test::scanner_image): what an automatic segmentation needs.
void write_synthetic_noisy_scan(const std::filesystem::path& dir, const std::string& prefix,
                                const Eigen::Vector3d& shift_mm);
// The same scan on an oblique LAS grid (i to the left, tilted 12 degrees)
// with the same field of view.
void write_synthetic_oblique_las_scan(const std::filesystem::path& dir, const std::string& prefix,
                                      const Eigen::Vector3d& shift_mm);

}  // namespace brainshift::e2e
