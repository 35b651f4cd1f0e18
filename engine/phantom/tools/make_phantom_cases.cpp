// Writes the standard phantom suite built on the default atlas, for benchmarks
// and for looking at the cases:
//   make_phantom_cases <atlas_cache_dir> <output_dir> [case_name]
// Per case: intraop_t1.nii.gz, intraop_labels.nii.gz, true_pullback_mm.nii.gz,
// landmarks.json, description.json, and truth_report.png (the report picture
// with the preop image moved by the rigid part only vs by the true field).
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>

#include "atlas/default_atlas.h"
#include "label_table_file.h"
#include "core/timer.h"
#include "image/nifti_io.h"
#include "image/resample.h"
#include "phantom/brain_shift_phantom.h"
#include "pipeline/scan_report.h"
#include "report/report.h"

namespace bs = brainshift;

namespace {

// Preop images pulled onto the intraop grid through per-voxel preop points.
template <class PreopPoint>
void warp(const bs::ImageF& t1, const bs::LabelImage& labels, const bs::Grid3& grid, PreopPoint&& preop_point,
          bs::ImageF& t1_out, bs::LabelImage& labels_out) {
  t1_out = bs::ImageF(grid, 0.f);
  labels_out = bs::LabelImage(grid, 0);
  for (int k = 0; k < grid.dims[2]; ++k)
    for (int j = 0; j < grid.dims[1]; ++j)
      for (int i = 0; i < grid.dims[0]; ++i) {
        const Eigen::Vector3d p = preop_point(i, j, k);
        t1_out.at(i, j, k) = bs::sample_linear(t1, p, 0.f);
        labels_out.at(i, j, k) = bs::sample_nearest(labels, p, 0);
      }
}

void write_case(const bs::DefaultAtlas& atlas, const bs::PhantomSpec& spec, const std::filesystem::path& dir) {
  bs::Stopwatch watch;
  const bs::PhantomCase pc = bs::make_phantom(atlas.t1, atlas.labels, spec);
  const double seconds = watch.seconds();
  std::filesystem::create_directories(dir);
  bs::write_scalar_image(dir / "intraop_t1.nii.gz", pc.intraop_t1, bs::VoxelType::int16);
  bs::write_label_image(dir / "intraop_labels.nii.gz", pc.intraop_labels);
  bs::write_displacement_field(dir / "true_pullback_mm.nii.gz", pc.true_pullback_mm);
  nlohmann::json landmarks = nlohmann::json::array();
  for (const auto& [x, p] : pc.landmarks_intraop_preop_mm)
    landmarks.push_back({{"intraop_mm", {x.x(), x.y(), x.z()}}, {"preop_mm", {p.x(), p.y(), p.z()}}});
  std::ofstream(dir / "landmarks.json") << landmarks.dump(1) << '\n';
  std::ofstream(dir / "description.json") << pc.description.dump(2) << '\n';

  const bs::Grid3& g = pc.intraop_t1.grid;
  const Eigen::Matrix4d back = pc.true_intraop_from_preop_rigid.inverse();
  bs::ImageF rigid_t1, true_t1;
  bs::LabelImage rigid_labels, true_labels;
  warp(atlas.t1, atlas.labels, g,
       [&](int i, int j, int k) { return Eigen::Vector3d((back * g.world_mm(i, j, k).homogeneous()).head<3>()); },
       rigid_t1, rigid_labels);
  warp(atlas.t1, atlas.labels, g,
       [&](int i, int j, int k) {
         return Eigen::Vector3d(g.world_mm(i, j, k) + pc.true_pullback_mm.vectors[g.index(i, j, k)].cast<double>());
       },
       true_t1, true_labels);
  bs::ReportOptions opt;
  opt.centre_label = bs::config::default_label_table().find("tumor")->value;
  if (pc.description.contains("sinking")) {
    const auto& c = pc.description["sinking"]["craniotomy_preop_mm"];
    const Eigen::Vector3d preop(c[0].get<double>(), c[1].get<double>(), c[2].get<double>());
    // Slices through a point 15 mm below the craniotomy, where the shift shows.
    const auto& gv = pc.description["sinking"]["gravity"];
    const Eigen::Vector3d gravity(gv[0].get<double>(), gv[1].get<double>(), gv[2].get<double>());
    opt.centre_mm = (pc.true_intraop_from_preop_rigid * (preop + 15 * gravity).homogeneous()).head<3>();
  }
  bs::ReportInputs in;
  in.intraop = &pc.intraop_t1;
  in.warped_preop_affine = &rigid_t1;
  in.warped_preop_nonrigid = &true_t1;
  in.warped_labels = &true_labels;
  in.legend = bs::report_legend(bs::config::default_label_table());
  in.outer_label = bs::atlas_labels::brain;
  // The truth, not a registration: row 2 is the rigid part alone, row 3 the
  // true field; there are no registration numbers to print.
  in.summary.scan_id = spec.name;
  in.summary.result_text = "Ground truth of the phantom: row 2 = the rigid part alone, row 3 = the true field";
  bs::write_report_png(dir / "truth_report.png", in, opt);
  std::printf("%-36s %.2f s  scale %.2f  min_jac %.3f  landmarks %zu\n", spec.name.c_str(), seconds,
              pc.description["nonrigid_scale_applied"].get<double>(), pc.description["min_jacobian"].get<double>(),
              pc.landmarks_intraop_preop_mm.size());
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) {
    std::cerr << "usage: make_phantom_cases <atlas_cache_dir> <output_dir> [case_name]\n";
    return 2;
  }
  try {
    const bs::DefaultAtlas atlas = bs::load_or_build_default_atlas(argv[1]);
    for (const auto& spec : bs::standard_phantom_suite())
      if (argc < 4 || spec.name == argv[3]) write_case(atlas, spec, std::filesystem::path(argv[2]) / spec.name);
  } catch (const std::exception& e) {
    std::cerr << "make_phantom_cases: " << e.what() << '\n';
    return 1;
  }
  return 0;
}
