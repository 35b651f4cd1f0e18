#include "segmentation/intraop_segmentation.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <optional>

#include "core/errors.h"
#include "core/parallel.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "registration/boundary_samples.h"
#include "registration/linear_sampler.h"
#include "segmentation/fluid_caps.h"
#include "segmentation/fluid_rim.h"

namespace brainshift::segmentation {
namespace {

ImageF crop_image(const ImageF& image, const VoxelBox& box, const Grid3& cropped) {
  ImageF out(cropped, 0.f);
  for (int k = 0; k < cropped.dims[2]; ++k)
    for (int j = 0; j < cropped.dims[1]; ++j) {
      const float* src = &image.voxels[image.grid.index(box.lo[0], j + box.lo[1], k + box.lo[2])];
      std::copy(src, src + cropped.dims[0], &out.voxels[cropped.index(0, j, k)]);
    }
  return out;
}

// The separation, in pooled sd's, between the ventricle class and the
// parenchyma class farthest from it among the major ones
// (kMajorClassWeight): the ventricles' wall is placed by the strongest edge of
// tissue around them (white matter in T1 and T2: the corpus callosum, the
// periventricular white matter), and a lighter or nearer class of grey matter
// and partial volume (sulcal fluid, the cortex under a craniotomy) does not
// hide it. Where no major class stands apart, the image cannot show them.
double fluid_contrast_sd(const std::vector<GaussianClass>& classes) {
  double best = -1;
  bool any = false;
  for (const auto& v : classes) {
    if (v.tissue != Tissue::ventricle) continue;
    for (const auto& p : classes)
      if (p.tissue == Tissue::parenchyma && p.weight >= kMajorClassWeight) {
        any = true;
        best = std::max(best, std::abs(v.mean - p.mean) / std::sqrt(v.sd * v.sd + p.sd * p.sd));
      }
  }
  return any ? best : std::numeric_limits<double>::infinity();
}

// Median and robust sd (interquartile range / 1.349) of the bias-corrected
// intensities in a mask.
std::pair<double, double> robust_stats(const ImageF& image, const std::vector<float>& bias, const Mask& m) {
  std::vector<double> x;
  for (std::size_t v = 0; v < m.voxels.size(); ++v)
    if (m.voxels[v]) x.push_back(image.voxels[v] / bias[v]);
  if (x.size() < 10) return {0, -1};
  std::sort(x.begin(), x.end());
  const auto at = [&](double q) { return x[static_cast<std::size_t>(q * static_cast<double>(x.size() - 1))]; };
  return {at(0.5), (at(0.75) - at(0.25)) / 1.349};
}

// The ventricles' wall contrast, in pooled robust sd's: the segmented
// ventricles against the parenchyma one to three voxels around them (the
// first voxel is partial volume). Whatever the classes, this is what places
// the wall: an image whose fluid looks like the tissue around it cannot show
// the ventricles. Infinite when too few voxels to say.
double ventricle_wall_contrast_sd(const ImageF& image, const std::vector<float>& bias, const Mask& ventricle,
                                  const Mask& brain) {
  const double h = ventricle.grid.spacing_mm().minCoeff();
  const Mask inner = dilate(ventricle, 1.01 * h), outer = dilate(ventricle, 3.01 * h);
  Mask shell(ventricle.grid, 0);
  for (std::size_t v = 0; v < shell.voxels.size(); ++v)
    shell.voxels[v] = outer.voxels[v] && !inner.voxels[v] && brain.voxels[v];
  const auto [mv, sv] = robust_stats(image, bias, ventricle);
  const auto [ms, ss] = robust_stats(image, bias, shell);
  if (sv < 0 || ss < 0) return std::numeric_limits<double>::infinity();
  return std::abs(mv - ms) / std::max(std::sqrt(sv * sv + ss * ss), 1e-9);
}

// Fluid classified as ventricle is ventricle only in components that reach
// the carried ventricles: a fluid pocket elsewhere in the brain (a resection
// cavity, fluid under the craniotomy) looks the same but is not.
void keep_carried_ventricles(Mask& brain, Mask& ventricle, const Mask& carried_ventricles) {
  int count = 0;
  const auto components = connected_components(ventricle, 6, &count);
  std::vector<bool> keep(static_cast<std::size_t>(count) + 1, false);
  for (std::size_t v = 0; v < ventricle.voxels.size(); ++v)
    if (carried_ventricles.voxels[v]) keep[static_cast<std::size_t>(components.voxels[v])] = true;
  for (std::size_t v = 0; v < ventricle.voxels.size(); ++v)
    if (ventricle.voxels[v] && !keep[static_cast<std::size_t>(components.voxels[v])]) {
      ventricle.voxels[v] = 0;
      brain.voxels[v] = 0;
    }
}

// A Gaussian class's log density, its share left out.
double log_density(const GaussianClass& g, double x) {
  const double z = (x - g.mean) / g.sd;
  return -std::log(g.sd) - 0.5 * z * z;
}

// The fluid test of a bias-corrected intensity: likelier under the
// ventricles' class than under any parenchyma class (each class's density
// alone, not its share: however rare a tissue of the brain, the intensity is
// compared with it).
bool likelier_fluid(const std::vector<GaussianClass>& classes, double x) {
  double best_fluid = -std::numeric_limits<double>::infinity(), best_tissue = best_fluid;
  for (const auto& c : classes) {
    if (c.tissue == Tissue::ventricle) best_fluid = std::max(best_fluid, log_density(c, x));
    else if (c.tissue == Tissue::parenchyma) best_tissue = std::max(best_tissue, log_density(c, x));
  }
  return best_fluid > best_tissue;
}

// Where the fluid test turns: from the fluid class's mean toward the nearest
// parenchyma class's (the tissue that borders fluid: grey matter in a T1),
// the first intensity the test no longer calls fluid. turn == fluid_mean
// when the classes give no such point.
struct FluidTurn {
  double fluid_mean = 0, turn = 0, tissue_mean = 0;
};
FluidTurn fluid_boundary(const std::vector<GaussianClass>& classes) {
  const GaussianClass* fluid = heaviest_class(classes, Tissue::ventricle);
  if (!fluid) return {};
  const GaussianClass* tissue = nullptr;
  for (const auto& c : classes)
    if (c.tissue == Tissue::parenchyma && (!tissue || std::abs(c.mean - fluid->mean) < std::abs(tissue->mean - fluid->mean)))
      tissue = &c;
  if (!tissue) return {fluid->mean, fluid->mean, fluid->mean};
  const int steps = 1000;
  for (int s = 1; s <= steps; ++s) {
    const double x = fluid->mean + (tissue->mean - fluid->mean) * s / steps;
    if (!likelier_fluid(classes, x)) return {fluid->mean, x, tissue->mean};
  }
  return {fluid->mean, tissue->mean, tissue->mean};
}

// The tissue beside a component of open fluid (raw_ratio_to_tissue_beside):
// within 3 mm of it, the cortex beneath a sinking's gap (2.5-3 mm of grey
// matter) and a voxel of partial volume at the wall, near enough that a
// coil's field (varying over centimetres) is the same on both sides.
constexpr double kTissueBesideMm = 3.0;

// Raw intensities of a component (its voxels, component == c) and of the
// brain tissue beside it (brain, neither fluid nor ventricle, within
// shell_mm of it): their medians' ratio, or NaN when either is empty.
// Both are read in the image as recorded: over a few millimetres a coil's
// field is the same on both sides of the component's wall, so the ratio is
// the tissues' own, whatever bias the classes were fitted with.
double raw_ratio_to_tissue_beside(const ImageF& image, const Image3<std::int32_t>& components, int c, const Mask& brain,
                                  const Mask& fluid, const Mask& ventricle, double shell_mm) {
  Mask own(components.grid, 0);
  for (std::size_t v = 0; v < own.voxels.size(); ++v) own.voxels[v] = components.voxels[v] == c;
  const VoxelBox box = grow_box(bounding_box_voxels(own), own.grid, shell_mm + own.grid.spacing_mm().maxCoeff());
  if (box.empty) return std::numeric_limits<double>::quiet_NaN();
  const Mask near = dilate(crop_to_box(own, box), shell_mm);
  std::vector<float> inside, beside;
  const Grid3& g = near.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        if (!near.at(i, j, k)) continue;
        const std::size_t w = own.grid.index(i + box.lo[0], j + box.lo[1], k + box.lo[2]);
        if (own.voxels[w]) inside.push_back(image.voxels[w]);
        else if (brain.voxels[w] && !fluid.voxels[w] && !ventricle.voxels[w]) beside.push_back(image.voxels[w]);
      }
  if (inside.empty() || beside.empty()) return std::numeric_limits<double>::quiet_NaN();
  const double tissue = median_in_place(beside);
  return tissue > 0 ? median_in_place(inside) / tissue : std::numeric_limits<double>::quiet_NaN();
}

// The gap a sinking left that the classification itself called outside:
// fluid (bias-corrected intensity within 2 sd of the fluid class's mean,
// where 95 % of its voxels lie, and nearer it than any parenchyma class's,
// which keeps the cortex's partial volume out) inside the carried outline, outside
// the classified brain (before the rules below move anything) and
// ventricles, thicker than any sulcus (it survives an opening of radius
// max_sulcus_half_width_mm), in bodies of at least min_gap_ml touching the
// carried outline's surface. Where no parenchyma class spans the fluid (a
// FLAIR-like image: tissue_em.h), the gap never enters the brain, so the
// open-fluid rule below never moves it out nor counts it; the brain-volume
// gate allows for it as for the fluid that rule moves (docs/PERFORMANCE.md
// 12.37). Returns its volume, ml.
double gap_left_outside_ml(const ImageF& image, const std::vector<float>& bias, const std::vector<GaussianClass>& classes,
                           const Mask& brain, const Mask& ventricle, const Mask& carried_outline,
                           double max_sulcus_half_width_mm, double min_gap_ml) {
  const GaussianClass* fluid = heaviest_class(classes, Tissue::ventricle);
  const GaussianClass* bulk = heaviest_class(classes, Tissue::parenchyma);
  if (!fluid || !bulk || max_sulcus_half_width_mm <= 0) return 0.0;
  const Grid3& g = brain.grid;
  Mask left(g, 0);
  for (std::size_t v = 0; v < left.voxels.size(); ++v) {
    if (!carried_outline.voxels[v] || brain.voxels[v] || ventricle.voxels[v]) continue;
    const double x = image.voxels[v] / bias[v];
    bool fluid_like = std::abs(x - fluid->mean) < 2 * fluid->sd;
    for (const auto& c : classes)
      if (c.tissue == Tissue::parenchyma) fluid_like = fluid_like && std::abs(x - fluid->mean) < std::abs(x - c.mean);
    left.voxels[v] = fluid_like;
  }
  // Less fluid left outside than one gap holds: no gap, after one pass over
  // the voxels (0.01-0.04 s a round on the daemon's phantom otherwise).
  const double voxel_ml = g.spacing_mm().prod() / 1000.0;
  if (static_cast<double>(count_nonzero(left)) * voxel_ml < min_gap_ml) return 0.0;
  // The rest on the fluid's box, grown beyond the opening's reach and a
  // voxel more, so that the box's faces (outside to boundary_voxels) lie
  // where no opened fluid reaches.
  const VoxelBox box = grow_box(bounding_box_voxels(left), g, max_sulcus_half_width_mm + 2 * g.spacing_mm().maxCoeff());
  const Mask opened = open(crop_to_box(left, box), max_sulcus_half_width_mm);
  const Mask surface = boundary_voxels(crop_to_box(carried_outline, box));
  int count = 0;
  const auto pieces = connected_components(opened, 6, &count);
  std::vector<std::size_t> voxels(static_cast<std::size_t>(count) + 1, 0);
  std::vector<std::uint8_t> at_surface(static_cast<std::size_t>(count) + 1, 0);
  for (std::size_t v = 0; v < opened.voxels.size(); ++v) {
    if (!opened.voxels[v]) continue;
    ++voxels[pieces.voxels[v]];
    at_surface[pieces.voxels[v]] |= surface.voxels[v];
  }
  double ml = 0;
  for (int c = 1; c <= count; ++c)
    if (at_surface[c] && voxels[c] * voxel_ml >= min_gap_ml) ml += voxels[c] * voxel_ml;
  return ml;
}

// Fluid labelled parenchyma that is thicker than any sulcus (it survives an
// opening of radius max_sulcus_half_width_mm) and lies open to what is
// outside the brain (at most a cap, drop_beyond_open_fluid, between) is not
// in the brain: the gap
// a sunken cortex leaves under the craniotomy, a cavity open to the surface.
// The prior, carried from where the brain was, holds brain there, and a
// parenchyma class stretched over the sulci's fluid and partial volume
// explains the fluid as well as the fluid class does: the image alone does
// not move it out, its shape does. Returns the voxels moved out.
struct OpenFluid {
  Mask moved;                          // the gap's fluid, moved out of the brain
  double next_to_ventricles_ml = 0;    // thick fluid left in: continuous with the ventricles
  double partial_fluid_ml = 0;         // left in: its median, or its raw ratio to the tissue beside it, nearer the turn
  double fluid_before_ml = 0;          // left in: fluid in the preop as well (a cistern, a fissure)
  nlohmann::json components = nlohmann::json::array();  // diagnostic: each open component >= min_gap_ml
};
OpenFluid open_fluid(const ImageF& image, const std::vector<float>& bias, const std::vector<GaussianClass>& classes,
                     const Mask& brain, const Mask& ventricle, const Mask& carried_ventricles,
                     const Mask& carried_outline, double max_sulcus_half_width_mm, double max_cap_mm,
                     double min_gap_ml, double max_median_toward_turn, const PreopSeen* seen,
                     const Mask& resectable, double min_preop_toward_tissue) {
  // Fluid: a bias-corrected intensity likelier under the ventricles' class
  // than under any parenchyma class (each class's density alone, not its
  // share: however rare a tissue of the brain, the intensity is compared
  // with it). The same cerebrospinal fluid fills the ventricles, the sulci,
  // the gap under a craniotomy and a cavity.
  // The outside is what lies beyond the brain's outline: a hole inside it (a
  // fluid pocket keep_carried_ventricles took out, a cavity) is not where a
  // gap opens to. Counted as outside, it made the fluid around the posterior
  // third ventricle 51 mm deep a "gap" (docs/PERFORMANCE.md 12.9).
  Mask fluid(brain.grid, 0), outside = fill_holes(brain);
  parallel_halves(fluid.voxels.size(), 1 << 16, [&](std::size_t begin, std::size_t end) {  // each voxel on its own
    for (std::size_t v = begin; v < end; ++v) {
      outside.voxels[v] = !outside.voxels[v];
      if (!brain.voxels[v] || ventricle.voxels[v]) continue;
      fluid.voxels[v] = likelier_fluid(classes, image.voxels[v] / bias[v]);
    }
  });
  // Noise makes single voxels of a fluid layer look like tissue (a few per
  // cent at the lowest SNR), and each such hole would erode the opening by
  // its radius: holes of one voxel are closed first.
  const Mask thick = open(close(fluid, brain.grid.spacing_mm().minCoeff()), max_sulcus_half_width_mm);
  // Open: with at most a cap (drop_beyond_open_fluid) between it and the outside.
  const Mask near_outside = dilate(outside, max_sulcus_half_width_mm + max_cap_mm);
  int count = 0;
  const auto components = connected_components(thick, 6, &count);
  std::vector<bool> open_to_outside(static_cast<std::size_t>(count) + 1, false);
  std::vector<std::size_t> size(static_cast<std::size_t>(count) + 1, 0);
  for (std::size_t v = 0; v < thick.voxels.size(); ++v) {
    const auto c = static_cast<std::size_t>(components.voxels[v]);
    ++size[c];
    if (thick.voxels[v] && near_outside.voxels[v]) open_to_outside[c] = true;
  }
  // A gap, not a cistern: the basal and sylvian cisterns are thick fluid
  // open to the outside too, but hold a few ml each.
  const double voxel_ml = std::abs(brain.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
  for (std::size_t c = 1; c < size.size(); ++c)
    if (static_cast<double>(size[c]) * voxel_ml < min_gap_ml) open_to_outside[c] = false;
  // No open component: nothing to move, nor to describe (what follows costs
  // a dilation and two distance maps, about 40 ms).
  if (std::none_of(open_to_outside.begin(), open_to_outside.end(), [](bool open) { return open; })) {
    OpenFluid none;
    none.moved = Mask(brain.grid, 0);
    return none;
  }
  // Nor the ventricular system: thick fluid that touches the ventricles
  // (segmented, or carried from the preop; within a voxel of them) is the
  // same fluid, a horn or a third ventricle a coarse preop map lacks. The
  // opening keeps thick fluid up to where the ventricles' label takes over.
  // A sinking's gap lies outside the cortex, the whole cerebral mantle away
  // from them (on the suite's 18 mm vertex sinking its gap came no nearer
  // than 8 mm).
  Mask any_ventricle = ventricle;
  for (std::size_t v = 0; v < any_ventricle.voxels.size(); ++v)
    any_ventricle.voxels[v] = ventricle.voxels[v] || carried_ventricles.voxels[v];
  const Mask near_ventricles = dilate(any_ventricle, 1.01 * brain.grid.spacing_mm().maxCoeff());
  std::vector<bool> ventricular(size.size(), false);
  for (std::size_t v = 0; v < thick.voxels.size(); ++v)
    if (thick.voxels[v] && near_ventricles.voxels[v]) ventricular[static_cast<std::size_t>(components.voxels[v])] = true;
  OpenFluid out;
  out.moved = Mask(brain.grid, 0);
  {
    const ImageF to_ventricles = distance_to_mask_mm(any_ventricle);
    Mask carried_outside = carried_outline;
    for (auto& v : carried_outside.voxels) v = !v;
    const ImageF depth = distance_to_mask_mm(carried_outside);
    std::vector<double> near(size.size(), 1e9), deep(size.size(), 0);
    std::vector<Eigen::Vector3d> sum(size.size(), Eigen::Vector3d::Zero());
    std::vector<std::vector<float>> intensities(size.size()), preop(size.size());
    const Grid3& g = brain.grid;
    const bool use_preop = seen && seen->image && seen->tissue_median != seen->fluid_median;
    std::optional<LinearSampler> preop_sampler;
    if (use_preop) preop_sampler.emplace(*seen->image);
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          const std::size_t v = g.index(i, j, k);
          const auto c = static_cast<std::size_t>(components.voxels[v]);
          if (c == 0 || !open_to_outside[c]) continue;
          near[c] = std::min<double>(near[c], to_ventricles.voxels[v]);
          deep[c] = std::max<double>(deep[c], depth.voxels[v]);
          sum[c] += g.world_mm(i, j, k);
          intensities[c].push_back(image.voxels[v] / bias[v]);
          double before = 0;
          if (!use_preop) continue;
          if (!resectable.voxels.empty() && resectable.voxels[v]) before = seen->tissue_median;
          else if (!preop_sampler->sample((seen->preop_from_intraop * g.world_mm(i, j, k).homogeneous()).head<3>(),
                                          &before, nullptr))
            continue;  // beyond the preop image: no evidence either way
          preop[c].push_back(static_cast<float>(before));
        }
    // A gap is a body of fluid: its intensities lie about the fluid's, and
    // their median nearer the fluid class's mean than where the fluid test
    // turns. Tissue whose voxels hold part fluid (a cortex with sulcal fluid
    // finer than a voxel, which every outline counts as brain) passes the
    // test only where noise takes it across: its median lies at the turn
    // (docs/DESIGN.md "Automatic intraop segmentation", item 7).
    const FluidTurn t = fluid_boundary(classes);
    // 0 at the fluid class's mean, 1 where the fluid test turns.
    const auto toward_turn_of = [&](double x) {
      return t.turn != t.fluid_mean ? (x - t.fluid_mean) / (t.turn - t.fluid_mean) : 0.0;
    };
    for (std::size_t c = 1; c < size.size(); ++c)
      if (open_to_outside[c]) {
        const Eigen::Vector3d m = sum[c] / static_cast<double>(size[c]);
        const double median = median_in_place(intensities[c]);
        const double toward_turn = toward_turn_of(median);
        // The same test against the tissue beside it in the raw image: a
        // fitted bias that bends at the brain's edge (a quadratic taking
        // the deep grey matter's and enlarged ventricles' partial volume
        // for a field, steep where it extrapolates) makes tissue there look
        // like fluid once corrected, never darker than the tissue beside it
        // (docs/DESIGN.md "Automatic intraop segmentation", item 7).
        const double ratio = raw_ratio_to_tissue_beside(image, components, static_cast<int>(c), brain, fluid,
                                                        ventricle, kTissueBesideMm);
        const double local_toward_turn = std::isfinite(ratio) ? toward_turn_of(ratio * t.tissue_mean) : 0.0;
        nlohmann::json record = {{"ml", static_cast<double>(size[c]) * voxel_ml}, {"ventricles_mm", near[c]},
                                 {"max_depth_mm", deep[c]}, {"centroid_mm", {m[0], m[1], m[2]}},
                                 {"median_intensity", median}, {"median_toward_fluid_turn", toward_turn},
                                 {"raw_ratio_to_tissue_beside", std::isfinite(ratio) ? ratio : -1.0},
                                 {"beside_toward_fluid_turn", local_toward_turn}};
        // What the preop held there: 0 at its fluid, 1 at its tissue.
        double preop_toward_tissue = 1;
        if (!preop[c].empty()) {
          preop_toward_tissue =
              (median_in_place(preop[c]) - seen->fluid_median) / (seen->tissue_median - seen->fluid_median);
          record["preop_toward_tissue"] = preop_toward_tissue;
        }
        out.components.push_back(record);
        if (toward_turn >= max_median_toward_turn || local_toward_turn >= max_median_toward_turn) {
          out.partial_fluid_ml += static_cast<double>(size[c]) * voxel_ml;
          open_to_outside[c] = false;
        } else if (preop_toward_tissue < min_preop_toward_tissue) {
          out.fluid_before_ml += static_cast<double>(size[c]) * voxel_ml;
          open_to_outside[c] = false;
        }
      }
  }
  for (std::size_t c = 1; c < size.size(); ++c)
    if (open_to_outside[c] && ventricular[c]) {
      out.next_to_ventricles_ml += static_cast<double>(size[c]) * voxel_ml;
      open_to_outside[c] = false;
    }
  for (std::size_t v = 0; v < thick.voxels.size(); ++v)
    out.moved.voxels[v] = thick.voxels[v] && brain.voxels[v] && !ventricle.voxels[v] &&
                          open_to_outside[static_cast<std::size_t>(components.voxels[v])];
  return out;
}

// A re-match sees the same image as the round before, under a prior carried
// by the non-rigid estimate instead of the head's placement. The gap a
// sinking leaves is centimetres wide and open to the craniotomy: the first
// round, under the wider prior, finds it too. What only the re-match calls
// open fluid lies where its narrower prior moved the outline onto fluid the
// brain borders anyway: the basal cisterns and the floor of the third
// ventricle under a swelling (docs/PERFORMANCE.md 12.9, 12.10), whose
// removal notched the outline and moved the field by up to 9 mm there. So a
// component of open fluid stands in the re-match only where it touches the
// gap found before, grown by a sulcus's half width (the same fluid, its
// edge classified a voxel apart).
void keep_gaps_found_before(Mask& moved, const Mask& found_before, const VoxelBox& box, double max_sulcus_half_width_mm) {
  if (count_nonzero(moved) == 0) return;
  Mask before(moved.grid, 0);
  if (found_before.grid.voxel_count() > 0) before = crop_to_box(found_before, box);
  const Mask near_before = dilate(before, max_sulcus_half_width_mm + moved.grid.spacing_mm().maxCoeff());
  int count = 0;
  const auto components = connected_components(moved, 6, &count);
  std::vector<bool> keep(static_cast<std::size_t>(count) + 1, false);
  for (std::size_t v = 0; v < moved.voxels.size(); ++v)
    if (moved.voxels[v] && near_before.voxels[v]) keep[static_cast<std::size_t>(components.voxels[v])] = true;
  for (std::size_t v = 0; v < moved.voxels.size(); ++v)
    moved.voxels[v] = moved.voxels[v] && keep[static_cast<std::size_t>(components.voxels[v])];
}

// Tissue on the far side of that fluid, between it and the skull (the dura,
// the inner table and their partial volume, cut obliquely by thick slices),
// is not brain either: the brain lies beneath the gap a sinking leaves, never
// beyond it. Along the ray through a brain voxel toward the carried brain's
// centre: fluid moved out on the inner side and what is outside the brain on
// the outer side, with less than max_cap_mm of brain between them, is such a
// cap. The cortex beneath the gap and gyri rising into it look inward into
// brain; a lobe beyond a cistern is thicker than a cap.
void drop_beyond_open_fluid(Mask& brain, const Mask& ventricle, const Mask& moved, const Eigen::Vector3d& centre_voxel,
                            double max_cap_mm, double max_sulcus_half_width_mm) {
  const Eigen::Vector3d spacing = brain.grid.spacing_mm();
  const Mask beyond = caps_beyond_fluid(brain, ventricle, moved, centre_voxel, max_cap_mm);
  for (std::size_t v = 0; v < brain.voxels.size(); ++v)
    if (beyond.voxels[v]) brain.voxels[v] = 0;
  // What is left of the cap where the gap thins out at its rim, and the falx
  // and sinus hanging into it: strands of "brain" next to the moved fluid
  // thinner than a sulcus is wide (a gyrus is thicker). The outer surface
  // would follow them into spikes.
  const Mask solid = open(brain, max_sulcus_half_width_mm);
  const Mask next_to_moved = dilate(moved, max_sulcus_half_width_mm + spacing.maxCoeff());
  for (std::size_t v = 0; v < brain.voxels.size(); ++v)
    if (brain.voxels[v] && !ventricle.voxels[v] && !solid.voxels[v] && next_to_moved.voxels[v]) brain.voxels[v] = 0;
  // The gap's floor is the cortex with its sulci opening into the gap; the
  // brain's outline is their hull (every outline counts the sulci in):
  // concavities narrower than a sulcus is wide are closed there, so that the
  // outer surface does not follow each sulcus into a fold.
  const Mask hull = close(brain, max_sulcus_half_width_mm);
  for (std::size_t v = 0; v < brain.voxels.size(); ++v)
    if (hull.voxels[v] && next_to_moved.voxels[v]) brain.voxels[v] = 1;
}

// Brain = the largest 6-connected component of parenchyma and ventricles;
// small enclosed holes are noise and take the likelier of the two tissues.
void clean_brain(Mask& brain, const std::array<std::vector<float>, kTissues>& q, Mask& ventricle,
                 double max_filled_hole_ml) {
  brain = largest_component(brain, 6);
  Mask holes = fill_holes(brain);
  for (std::size_t v = 0; v < holes.voxels.size(); ++v) holes.voxels[v] = holes.voxels[v] && !brain.voxels[v];
  int count = 0;
  const auto components = connected_components(holes, 6, &count);
  std::vector<std::size_t> size(static_cast<std::size_t>(count) + 1, 0);
  for (auto c : components.voxels) ++size[static_cast<std::size_t>(c)];
  const double voxel_ml = std::abs(brain.grid.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
  for (std::size_t v = 0; v < holes.voxels.size(); ++v) {
    const auto c = static_cast<std::size_t>(components.voxels[v]);
    if (c == 0 || size[c] * voxel_ml >= max_filled_hole_ml) continue;
    brain.voxels[v] = 1;
    ventricle.voxels[v] = q[1][v] > q[0][v];
  }
  for (std::size_t v = 0; v < brain.voxels.size(); ++v) ventricle.voxels[v] = ventricle.voxels[v] && brain.voxels[v];
}

// An earlier round's log bias on this round's box: its fitted polynomial
// where it has one (it extends smoothly beyond the box it was fitted in),
// else the log of its bias image.
std::vector<float> earlier_log_bias(const IntraopSegmentation& fitted, const VoxelBox& box, const Grid3& g) {
  if (fitted.bias_field) {
    std::array<int, 3> origin{};
    for (int a = 0; a < 3; ++a) origin[a] = box.lo[a] - fitted.bias_origin[a];
    return fitted.bias_field->log_bias_box(origin, g.dims);
  }
  if (!fitted.bias.grid.same_geometry(fitted.labels.grid) || fitted.bias.voxels.empty())
    throw InputError("segmentation: the earlier round has no bias to reuse");
  std::vector<float> out(g.voxel_count());
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        out[g.index(i, j, k)] = std::log(fitted.bias.at(i + box.lo[0], j + box.lo[1], k + box.lo[2]));
  return out;
}

nlohmann::json describe(const EmResult& em) {
  nlohmann::json classes = nlohmann::json::array();
  for (const auto& g : em.classes)
    classes.push_back({{"tissue", name_of(g.tissue)}, {"mean", g.mean}, {"sd", g.sd}, {"weight", g.weight},
                       {"band_weight", g.band_weight > 0 ? g.band_weight : g.weight},
                       {"surface_fluid", g.surface_fluid}});
  return {{"classes", classes}, {"iterations", em.iterations}, {"converged", em.converged},
          {"mean_log_likelihood", em.mean_log_likelihood}, {"samples", em.samples},
          {"parenchyma_classes_dropped", em.parenchyma_classes_dropped}};
}

}  // namespace

IntraopSegmentation segment_intraop(const ImageF& image, const LabelImage& carried_labels,
                                    std::uint16_t brain_label, const std::vector<std::uint16_t>& ventricle_labels,
                                    const SegmentationParameters& params, const IntraopSegmentation* fitted,
                                    const Mask* gap_found_before, const PreopSeen* preop_seen) {
  if (!image.grid.same_geometry(carried_labels.grid))
    throw InputError("segmentation: the image and the carried labels are on different grids");
  const Mask outline = outline_mask(carried_labels);
  const VoxelBox box = grow_box(bounding_box_voxels(outline), image.grid, params.margin_mm);
  if (box.empty) throw InputError("segmentation: the carried preop brain does not reach the intraop image");
  const Mask outline_box = crop_to_box(outline, box);
  const Mask ventricle_box = crop_to_box(mask_of_labels(carried_labels, ventricle_labels), box);
  const Grid3& g = outline_box.grid;
  const ImageF image_box = crop_image(image, box, g);

  PriorWidths widths;
  widths.outline_mm = params.prior_width_mm;
  widths.inward_mm = params.prior_inward_width_mm > 0 ? params.prior_inward_width_mm : params.prior_width_mm;
  widths.ventricle_mm = params.ventricle_prior_width_mm;
  widths.ventricle_shift_mm = params.ventricle_shift_mm;
  const TissuePrior prior = tissue_prior(outline_box, ventricle_box, widths, params.prior_floor);
  EmParameters em_params = params.em;
  em_params.fixed_ventricle_class = params.ventricle_shift_mm > 0;
  const EmResult em = fitted ? classify_with_classes(image_box, prior, fitted->classes,
                                                     earlier_log_bias(*fitted, box, g), em_params)
                             : fit_tissue_mixture(image_box, prior, em_params);

  Mask brain(g, 0), ventricle(g, 0);
  parallel_halves(g.voxel_count(), 1 << 16, [&](std::size_t begin, std::size_t end) {  // each voxel on its own
    for (std::size_t v = begin; v < end; ++v) {
      const float p = em.posterior[0][v], vent = em.posterior[1][v], out = em.posterior[2][v];
      brain.voxels[v] = std::max(p, vent) > out;
      ventricle.voxels[v] = vent > p && vent > out;
    }
  });
  keep_carried_ventricles(brain, ventricle, ventricle_box);
  const double left_outside_ml = gap_left_outside_ml(image_box, em.bias, em.classes, brain, ventricle, outline_box,
                                                     params.max_sulcus_half_width_mm, params.min_gap_ml);
  std::array<std::vector<float>, kTissues> posterior = em.posterior;
  Mask moved_out(g, 0), gap_fluid(g, 0);
  double open_fluid_ml = 0, ventricular_fluid_ml = 0, partial_fluid_ml = 0, fluid_before_ml = 0;
  nlohmann::json open_components = nlohmann::json::array();
  // The caps' rays (items 7 and 11) look toward the carried brain's centre.
  const Eigen::Vector3d centre_voxel = (g.voxel_from_world() * centroid_mm(outline_box).homogeneous()).head<3>();
  const Mask resectable_box = preop_seen && preop_seen->resectable.grid.same_geometry(image.grid)
                                  ? crop_to_box(preop_seen->resectable, box)
                                  : Mask{};
  if (params.max_sulcus_half_width_mm > 0) {
    OpenFluid found = open_fluid(image_box, em.bias, em.classes, brain, ventricle, ventricle_box, outline_box,
                                 params.max_sulcus_half_width_mm, params.max_cap_mm, params.min_gap_ml,
                                 params.max_gap_median_toward_fluid_turn, preop_seen, resectable_box,
                                 params.min_gap_preop_toward_tissue);
    open_components = found.components;
    moved_out = std::move(found.moved);
    if (gap_found_before) keep_gaps_found_before(moved_out, *gap_found_before, box, params.max_sulcus_half_width_mm);
    gap_fluid = moved_out;
    ventricular_fluid_ml = found.next_to_ventricles_ml;
    partial_fluid_ml = found.partial_fluid_ml;
    fluid_before_ml = found.fluid_before_ml;
    for (std::size_t v = 0; v < moved_out.voxels.size(); ++v) {
      if (!moved_out.voxels[v]) continue;
      brain.voxels[v] = 0;
      // The parenchyma's share was the fluid's, which is outside here.
      posterior[2][v] += posterior[0][v];
      posterior[0][v] = 0;
    }
    open_fluid_ml = volume_ml(moved_out);
    if (open_fluid_ml > 0) {
      Mask before = brain;
      drop_beyond_open_fluid(brain, ventricle, moved_out, centre_voxel, params.max_cap_mm,
                             params.max_sulcus_half_width_mm);
      for (std::size_t v = 0; v < brain.voxels.size(); ++v)
        if (before.voxels[v] && !brain.voxels[v]) {
          moved_out.voxels[v] = 1;
          posterior[2][v] += posterior[0][v];
          posterior[0][v] = 0;
        }
    }
  }
  // The bright fluid rim around a T2-like brain (item 11); nothing in a T1.
  const Mask rim = fluid_rim(brain, ventricle, image_box, em.bias, em.classes,
                             {params.max_fluid_rim_mm, params.max_rim_cap_mm, params.rim_cap_cavity_margin_mm,
                              params.min_fluid_contrast_sd},
                             resectable_box, centre_voxel);
  for (std::size_t v = 0; v < rim.voxels.size(); ++v) {
    if (!rim.voxels[v]) continue;
    brain.voxels[v] = 0;
    posterior[2][v] += posterior[0][v];
    posterior[0][v] = 0;
  }
  clean_brain(brain, posterior, ventricle, params.max_filled_hole_ml);

  IntraopSegmentation result;
  result.labels = LabelImage(image.grid, 0);
  result.confidence = ImageF(image.grid, 1.f);
  result.bias = ImageF(image.grid, 1.f);
  const std::uint16_t ventricle_value = ventricle_labels.empty() ? brain_label : ventricle_labels.front();
  for_each_voxel_on_both_cores(g.dims, [&](std::size_t v, int i, int j, int k) {
    const std::size_t w = image.grid.index(i + box.lo[0], j + box.lo[1], k + box.lo[2]);
    const int chosen = ventricle.voxels[v] ? 1 : brain.voxels[v] ? 0 : 2;
    result.labels.voxels[w] = chosen == 1 ? ventricle_value : chosen == 0 ? brain_label : 0;
    result.confidence.voxels[w] = posterior[chosen][v];
    result.bias.voxels[w] = em.bias[v];
  });
  // What the brain-volume gate allows for: the fluid moved out, and the gap
  // the classification itself left outside (gap_left_outside_ml).
  result.open_fluid_ml = open_fluid_ml + left_outside_ml;
  if (params.max_sulcus_half_width_mm > 0) {
    result.open_fluid = Mask(image.grid, 0);
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i)
          result.open_fluid.at(i + box.lo[0], j + box.lo[1], k + box.lo[2]) = gap_fluid.at(i, j, k);
  }
  result.classes = em.classes;
  if (fitted) {
    result.bias_field = fitted->bias_field;
    result.bias_origin = fitted->bias_origin;
  } else {
    result.bias_field = em.bias_field;
    result.bias_origin = box.lo;
  }
  result.report = describe(em);
  result.report["classes_from_earlier_round"] = fitted != nullptr;
  const double class_contrast = fluid_contrast_sd(em.classes);
  result.report["fluid_contrast_sd"] = std::isfinite(class_contrast) ? class_contrast : -1.0;
  const double wall_contrast = ventricle_wall_contrast_sd(image_box, em.bias, ventricle, brain);
  result.report["ventricle_wall_contrast_sd"] = std::isfinite(wall_contrast) ? wall_contrast : -1.0;
  result.report["prior_width_mm"] = params.prior_width_mm;
  result.report["bias_degree"] = params.em.bias_degree;
  result.report["ventricle_prior_width_mm"] = params.ventricle_prior_width_mm;
  result.report["ventricle_shift_mm"] = params.ventricle_shift_mm;
  result.report["prior_inward_width_mm"] = widths.inward_mm;
  result.report["brain_ml"] = volume_ml(brain);
  result.report["open_fluid_ml"] = open_fluid_ml;
  result.report["gap_left_outside_ml"] = left_outside_ml;
  result.report["beyond_open_fluid_ml"] = volume_ml(moved_out) - open_fluid_ml;
  result.report["open_fluid_next_to_ventricles_ml"] = ventricular_fluid_ml;
  result.report["open_fluid_partial_volume_ml"] = partial_fluid_ml;
  result.report["open_fluid_in_preop_ml"] = fluid_before_ml;
  result.report["open_fluid_components"] = open_components;
  result.report["fluid_rim_ml"] = volume_ml(rim);
  result.report["ventricles_ml"] = volume_ml(ventricle);
  const bool classes_apart = !std::isfinite(class_contrast) || class_contrast >= params.min_fluid_contrast_sd;
  const bool wall_apart = !std::isfinite(wall_contrast) || wall_contrast >= params.min_wall_contrast_sd;
  if (!classes_apart || !wall_apart)
    result.refusal = "the image does not separate ventricular fluid from brain tissue (" +
                     std::string(classes_apart ? "at the ventricles' wall " : "fitted classes ") +
                     std::to_string(classes_apart ? wall_contrast : class_contrast) + " sd apart, at least " +
                     std::to_string(classes_apart ? params.min_wall_contrast_sd : params.min_fluid_contrast_sd) +
                     " needed): not an MR contrast the automatic segmentation can use; fitted classes " +
                     result.report["classes"].dump();
  else if (count_nonzero(brain) == 0)
    result.refusal = "no brain tissue was found in the image";
  return result;
}

}  // namespace brainshift::segmentation
