// Where are a robustness case's worst landmarks, and which input makes them?
// Registers each case in the three input modes (labels + image, labels,
// image only) and prints, for every landmark whose error passes --over-mm in
// any mode, what it is near: its depth in the true brain and in the preop map
// the engine registers against, its distance to the true ventricles, the
// labels the stages saw at it (given segmentation, automatic segmentation,
// truth carried by the true field), its place in the slab, and the error of
// each mode (affine and non-rigid). A development tool (docs/PERFORMANCE.md
// 12.9); run it with --config to switch a stage off for the stage split.
//   brainshift_worst_landmarks_bench [--config FILE] [--atlas-cache DIR] [--cases a,b] [--over-mm MM]
#include <mpi.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <memory>
#include <set>

#include "atlas/default_atlas.h"
#include "bench_session.h"
#include "field/metrics.h"
#include "field/vector_sampling.h"
#include "field/warp.h"
#include "fem/petsc_session.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "image/resample.h"
#include "robustness_evaluation.h"

using namespace brainshift;

namespace {

Mask outline_of(const LabelImage& labels) {
  Mask m(labels.grid, 0);
  for (std::size_t v = 0; v < m.voxels.size(); ++v) m.voxels[v] = labels.voxels[v] != 0;
  return m;
}

nlohmann::json vec(const Eigen::Vector3d& v) { return {v[0], v[1], v[2]}; }

// Fraction of voxels within radius_mm of x (on labels' grid) that are brain.
double brain_fraction_near(const LabelImage& labels, const Eigen::Vector3d& x, double radius_mm) {
  const GridSampler at(labels.grid);
  std::size_t n = 0, brain = 0;
  for (double dx = -radius_mm; dx <= radius_mm; dx += 1)
    for (double dy = -radius_mm; dy <= radius_mm; dy += 1)
      for (double dz = -radius_mm; dz <= radius_mm; dz += 1) {
        if (dx * dx + dy * dy + dz * dz > radius_mm * radius_mm) continue;
        ++n;
        brain += at.nearest(labels.voxels, x + Eigen::Vector3d(dx, dy, dz), 0) != 0;
      }
  return n ? static_cast<double>(brain) / static_cast<double>(n) : 0.0;
}


// The largest connected pieces of `a and not b` (6-connected): volume,
// centroid, the share of it the truth calls ventricle, and the share inside
// the filled outline of `seg` (an enclosed hole rather than a notch).
nlohmann::json pieces(const Mask& a_not_b, const LabelImage& truth, const Mask& seg_filled, int top) {
  int count = 0;
  const auto comp = connected_components(a_not_b, 6, &count);
  struct Piece { std::size_t n = 0, ventricle = 0, enclosed = 0; Eigen::Vector3d sum = Eigen::Vector3d::Zero(); };
  std::vector<Piece> p(static_cast<std::size_t>(count) + 1);
  const Grid3& g = truth.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        const auto c = static_cast<std::size_t>(comp.voxels[v]);
        if (c == 0) continue;
        ++p[c].n;
        p[c].ventricle += truth.voxels[v] == atlas_labels::ventricles;
        p[c].enclosed += seg_filled.voxels[v] != 0;
        p[c].sum += g.world_mm(i, j, k);
      }
  std::sort(p.begin(), p.end(), [](const Piece& x, const Piece& y) { return x.n > y.n; });
  const double voxel_ml = std::abs(g.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
  nlohmann::json out = nlohmann::json::array();
  for (int t = 0; t < top && t < static_cast<int>(p.size()) && p[t].n > 0; ++t) {
    const double n = static_cast<double>(p[t].n);
    out.push_back({{"ml", n * voxel_ml}, {"centroid_mm", vec(p[t].sum / n)}, {"truth_ventricle_share", p[t].ventricle / n},
                   {"enclosed_share", p[t].enclosed / n}});
  }
  return out;
}

// Where the automatic segmentation and the truth carried by the true field
// disagree: brain it missed, and brain it added.
nlohmann::json segmentation_errors(const LabelImage& seg, const LabelImage& truth) {
  const Mask seg_brain = outline_of(seg), truth_brain = outline_of(truth), filled = fill_holes(seg_brain);
  Mask missed(seg.grid, 0), added(seg.grid, 0), vent_as_tissue(seg.grid, 0);
  for (std::size_t v = 0; v < missed.voxels.size(); ++v) {
    missed.voxels[v] = truth_brain.voxels[v] && !seg_brain.voxels[v];
    added.voxels[v] = seg_brain.voxels[v] && !truth_brain.voxels[v];
    vent_as_tissue.voxels[v] = truth.voxels[v] == atlas_labels::ventricles && seg.voxels[v] != atlas_labels::ventricles;
  }
  return {{"missed", pieces(missed, truth, filled, 5)}, {"added", pieces(added, truth, filled, 5)},
          {"truth_ventricle_not_segmented_ventricle", pieces(vent_as_tissue, truth, filled, 5)}};
}

struct PreopMaps {
  ImageF truth_brain_sd, truth_ventricle_sd, preop_brain_sd;
  const ImageF* preop_t1 = nullptr;  // the T1 the truth's intensities come from
};

struct ModeResult {
  std::string mode;
  ScanResult scan;
  std::vector<double> nonrigid, affine;
};

ModeResult run_mode(EngineSession& session, const PhantomCase& c, const std::string& mode) {
  ScanInput scan;
  if (mode != "image") scan.labels = c.intraop_labels;
  if (mode != "labels") scan.image = c.intraop_t1;
  ModeResult m{mode, session.register_scan(scan, nullptr), {}, {}};
  std::vector<Eigen::Vector3d> x, p;
  const Eigen::Matrix4d preop_from_intraop = m.scan.intraop_from_preop.inverse();
  for (const auto& [xi, pi] : c.landmarks_intraop_preop_mm) {
    x.push_back(xi);
    p.push_back(pi);
    m.affine.push_back(((preop_from_intraop * xi.homogeneous()).head<3>() - pi).norm());
  }
  m.nonrigid = target_registration_error(m.scan.pullback_field_mm, x, p).errors_mm;
  return m;
}

nlohmann::json landmark_record(std::size_t i, const PhantomCase& c, const LabelImage& truth_intraop,
                               const PreopMaps& maps, const std::vector<ModeResult>& modes) {
  const auto& [x, p] = c.landmarks_intraop_preop_mm[i];
  const Grid3& g = c.intraop_labels.grid;
  const GridSampler preop(maps.truth_brain_sd.grid), intraop(g);
  const Eigen::Vector3d ijk = intraop.voxel(x);
  const double slab_edge_mm = std::min(ijk[2], g.dims[2] - 1 - ijk[2]) * g.spacing_mm()[2];
  nlohmann::json r = {{"index", i}, {"x_intraop", vec(x)}, {"p_preop", vec(p)}, {"true_shift_mm", (x - p).norm()},
                      {"truth_depth_mm", -preop.linear(maps.truth_brain_sd.voxels, p, 1e3f)},
                      {"preop_map_depth_mm", -preop.linear(maps.preop_brain_sd.voxels, p, 1e3f)},
                      {"truth_ventricle_mm", preop.linear(maps.truth_ventricle_sd.voxels, p, 1e3f)},
                      {"slab_edge_mm", slab_edge_mm}, {"slice", ijk[2]},
                      {"preop_t1_at_p", preop.linear(maps.preop_t1->voxels, p, 0.f)},
                      {"intraop_t1_at_x", intraop.linear(c.intraop_t1.voxels, x, 0.f)},
                      {"truth_label", intraop.nearest(truth_intraop.voxels, x, 0)},
                      {"given_label", intraop.nearest(c.intraop_labels.voxels, x, 0)},
                      {"truth_brain_3mm", brain_fraction_near(truth_intraop, x, 3)},
                      {"given_brain_3mm", brain_fraction_near(c.intraop_labels, x, 3)}};
  for (const auto& m : modes) {
    nlohmann::json e = {{"nonrigid_mm", m.nonrigid[i]}, {"affine_mm", m.affine[i]}};
    const auto u = sample_vector_linear(m.scan.pullback_field_mm, x);
    if (u) e["error_vector_mm"] = vec(x + *u - p);
    if (m.scan.intraop_labels) {
      e["segmented_label"] = intraop.nearest(m.scan.intraop_labels->voxels, x, 0);
      e["segmented_brain_3mm"] = brain_fraction_near(*m.scan.intraop_labels, x, 3);
    }
    r[m.mode] = e;
  }
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  std::string config_path, atlas_cache = "brainshift-atlas";
  std::vector<std::string> only;
  double over_mm = 3.0;
  CLI::App app("the robustness suite's worst landmarks: where they are and which input makes them");
  app.add_option("--config", config_path);
  app.add_option("--atlas-cache", atlas_cache);
  app.add_option("--cases", only, "case names (default: all)")->delimiter(',');
  app.add_option("--over-mm", over_mm, "report landmarks over this error in any mode");
  CLI11_PARSE(app, argc, argv);

  PetscSession petsc;
  if (!bench::drive_from_this_rank()) return 0;
  const PipelineParameters params = bench::parameters(config_path);
  const evaluation::RobustnessInputs inputs = evaluation::load_robustness_inputs(atlas_cache);
  std::vector<RobustnessSpec> suite = robustness_suite_cases(only);
  for (const auto& spec : suite) {
    const evaluation::CaseAnatomy anatomy = evaluation::case_anatomy(inputs, spec);
    EngineSession session(MPI_COMM_WORLD, params);
    session.load_preop(anatomy.preop, nullptr);
    RobustnessSpec s = spec;
    s.phantom.preop_tumor.reset();  // already in anatomy (as run_robustness_case)
    const PhantomCase c = make_robustness_case(anatomy.preop.t1, anatomy.truth_labels, s);
    const LabelImage truth_intraop = warp_labels_nearest(anatomy.truth_labels, c.true_pullback_mm);
    PreopMaps maps{signed_distance_mm(outline_of(anatomy.truth_labels)),
                   signed_distance_mm(mask_of_labels(anatomy.truth_labels, {atlas_labels::ventricles})),
                   signed_distance_mm(outline_of(anatomy.preop.labels)), &anatomy.preop.t1};
    std::vector<ModeResult> modes;
    for (const char* mode : {"labels+image", "labels", "image"}) modes.push_back(run_mode(session, c, mode));
    nlohmann::json out = {{"case", spec.phantom.name}, {"description", c.description}, {"modes", {}}, {"landmarks", {}}};
    for (const auto& m : modes) {
      double worst = 0;
      int over = 0;
      for (double e : m.nonrigid) {
        worst = std::max(worst, e);
        over += e > over_mm;
      }
      double sum = 0;
      for (double e : m.nonrigid) sum += e;
      out["modes"][m.mode] = {{"kind", std::string(protocol::to_string(m.scan.kind))},
                              {"mean_mm", m.nonrigid.empty() ? 0.0 : sum / static_cast<double>(m.nonrigid.size())},
                              {"p95_mm", percentile(m.nonrigid, 95.0)}, {"worst_mm", worst},
                              {"over", over}, {"metrics", m.scan.metrics}};
      if (m.scan.intraop_labels)
        out["modes"][m.mode]["segmentation_dice"] = evaluation::segmentation_dice(
            *m.scan.intraop_labels, anatomy.truth_labels, c.true_pullback_mm, spec.phantom.resection.enabled,
            spec.phantom.resection.tumor_label);
      if (m.scan.intraop_labels) out["modes"][m.mode]["segmentation_errors"] = segmentation_errors(*m.scan.intraop_labels, truth_intraop);
    }
    for (std::size_t i = 0; i < c.landmarks_intraop_preop_mm.size(); ++i) {
      bool bad = false;
      for (const auto& m : modes) bad |= m.nonrigid[i] > over_mm;
      if (bad) out["landmarks"].push_back(landmark_record(i, c, truth_intraop, maps, modes));
    }
    std::printf("%s\n", out.dump().c_str());
    std::fflush(stdout);
  }
  return 0;
}
