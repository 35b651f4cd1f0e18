#include "segmentation/open_fluid.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>

#include "core/parallel.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "registration/linear_sampler.h"
#include "segmentation/fluid_caps.h"

namespace brainshift::segmentation {
namespace {

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

}  // namespace

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

}  // namespace brainshift::segmentation
