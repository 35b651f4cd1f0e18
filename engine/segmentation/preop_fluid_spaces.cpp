#include "segmentation/preop_fluid_spaces.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "image/resample.h"

namespace brainshift::segmentation {
namespace {

// Nearer a fluid reference than a tissue one (either contrast: T1's dark
// fluid or T2's bright one).
bool nearer_fluid(double value, double fluid, double tissue) { return std::abs(value - fluid) < std::abs(value - tissue); }

// Median of the image over the given labels' voxels of one value; NaN without any.
double median_over(const ImageF& image, const LabelImage& labels, std::uint16_t value) {
  std::vector<float> v;
  for (std::size_t i = 0; i < labels.voxels.size(); ++i)
    if (labels.voxels[i] == value) v.push_back(image.voxels[i]);
  return v.empty() ? std::nan("") : median_in_place(v);
}

}  // namespace

PreopFluidSpaces adopt_preop_fluid_spaces(const PreopFluidSpacesInput& in, const PreopFluidSpacesParameters& p) {
  const Grid3& g = in.given.grid;
  if (in.intraop_image && !in.intraop_image->grid.same_geometry(g))
    throw InputError("fluid spaces: the intraop image and the given labels are on different grids");
  PreopFluidSpaces out{in.given, 0.0, {}};
  const double voxel_ml = g.spacing_mm().prod() / 1000.0;
  // The preop's own fluid and tissue must differ, else nothing tells them apart.
  if (!(std::abs(in.preop_fluid_median - in.preop_tissue_median) > 0)) {
    out.report = {{"applied", false}, {"why", "the preop shows no fluid apart from tissue"}};
    return out;
  }
  double intraop_fluid = std::nan(""), intraop_tissue = std::nan("");
  if (in.intraop_image && in.ventricle_label != 0) {
    intraop_fluid = median_over(*in.intraop_image, in.given, in.ventricle_label);
    intraop_tissue = median_over(*in.intraop_image, in.given, in.brain_label);
  }
  const bool image_test = std::isfinite(intraop_fluid) && std::isfinite(intraop_tissue) && intraop_fluid != intraop_tissue;

  // Candidates: left out by the given labels, brain in the placed preop,
  // fluid in the intraop image (when it can tell).
  const Eigen::Matrix4d preop_from_intraop = in.intraop_from_preop.inverse();
  const LabelImage preop_here = resample_nearest(in.preop_labels, g, preop_from_intraop);
  Mask candidate(g, 0);
  parallel_halves(g.voxel_count(), 1 << 16, [&](std::size_t begin, std::size_t end) {
    for (std::size_t v = begin; v < end; ++v)
      candidate.voxels[v] = in.given.voxels[v] == 0 && preop_here.voxels[v] == in.brain_label &&
                            (!image_test || nearer_fluid(in.intraop_image->voxels[v], intraop_fluid, intraop_tissue));
  });
  // The opening and the components on the candidates' box, grown by more
  // than the opening reaches (a voxel beyond its radius): the same spaces as
  // on the whole grid, at the cost of the brain's rim instead of the scan.
  const VoxelBox found = bounding_box_voxels(candidate);
  if (found.empty) {
    out.report = {{"applied", true}, {"added_ml", 0.0}, {"not_fluid_before_ml", 0.0},
                  {"intraop_image_test", image_test}, {"spaces_of_half_a_ml_or_more", nlohmann::json::array()}};
    return out;
  }
  const VoxelBox box = grow_box(found, g, p.min_half_width_mm + g.spacing_mm().maxCoeff());
  const Mask wide = open(crop_to_box(candidate, box), p.min_half_width_mm);
  const Grid3& gb = wide.grid;
  int count = 0;
  const auto components = connected_components(wide, 6, &count);
  std::vector<std::size_t> size(static_cast<std::size_t>(count) + 1, 0), fluid(size.size(), 0);
  const GridSampler preop_t1(in.preop_t1.grid);
  const Eigen::Matrix4d preop_from_voxel = preop_from_intraop * gb.world_from_voxel;
  for (int k = 0; k < gb.dims[2]; ++k)
    for (int j = 0; j < gb.dims[1]; ++j)
      for (int i = 0; i < gb.dims[0]; ++i) {
        const std::size_t v = gb.index(i, j, k);
        const auto c = static_cast<std::size_t>(components.voxels[v]);
        if (c == 0) continue;
        ++size[c];
        const Eigen::Vector3d at = (preop_from_voxel * Eigen::Vector4d(i, j, k, 1.0)).head<3>();
        const float before = preop_t1.linear(in.preop_t1.voxels, at, static_cast<float>(in.preop_tissue_median));
        fluid[c] += nearer_fluid(before, in.preop_fluid_median, in.preop_tissue_median);
      }
  std::vector<char> adopt(size.size(), 0);
  nlohmann::json spaces = nlohmann::json::array();
  double refused_ml = 0;
  for (std::size_t c = 1; c < size.size(); ++c) {
    const double ml = static_cast<double>(size[c]) * voxel_ml;
    if (ml < p.min_space_ml) continue;
    const double fluid_fraction = static_cast<double>(fluid[c]) / static_cast<double>(size[c]);
    // Most of it fluid before the surgery: a space, not a gap a sinking opened.
    adopt[c] = fluid_fraction >= 0.5;
    if (adopt[c]) out.added_ml += ml;
    else refused_ml += ml;
    if (ml >= 0.5) spaces.push_back({{"ml", ml}, {"preop_fluid_fraction", fluid_fraction}, {"adopted", adopt[c] != 0}});
  }
  for (int k = 0; k < gb.dims[2]; ++k)
    for (int j = 0; j < gb.dims[1]; ++j)
      for (int i = 0; i < gb.dims[0]; ++i) {
        const auto c = static_cast<std::size_t>(components.voxels[gb.index(i, j, k)]);
        if (c != 0 && adopt[c]) out.labels.at(i + box.lo[0], j + box.lo[1], k + box.lo[2]) = in.brain_label;
      }
  out.report = {{"applied", true}, {"added_ml", out.added_ml}, {"not_fluid_before_ml", refused_ml},
                {"intraop_image_test", image_test}, {"spaces_of_half_a_ml_or_more", spaces}};
  return out;
}

}  // namespace brainshift::segmentation
