#include "segmentation/intraop_segmentation.h"

#include <algorithm>
#include <cmath>

#include "core/errors.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "registration/boundary_samples.h"

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
// parenchyma class farthest from it among those holding at least a sixth of
// the parenchyma: the ventricles' wall is placed by the strongest edge of
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
      if (p.tissue == Tissue::parenchyma && p.weight >= 1.0 / 6) {
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

nlohmann::json describe(const EmResult& em) {
  nlohmann::json classes = nlohmann::json::array();
  for (const auto& g : em.classes)
    classes.push_back({{"tissue", name_of(g.tissue)}, {"mean", g.mean}, {"sd", g.sd}, {"weight", g.weight}});
  return {{"classes", classes}, {"iterations", em.iterations}, {"converged", em.converged},
          {"mean_log_likelihood", em.mean_log_likelihood}};
}

}  // namespace

IntraopSegmentation segment_intraop(const ImageF& image, const LabelImage& carried_labels,
                                    std::uint16_t brain_label, const std::vector<std::uint16_t>& ventricle_labels,
                                    const SegmentationParameters& params) {
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
  const EmResult em = fit_tissue_mixture(image_box, prior, em_params);

  Mask brain(g, 0), ventricle(g, 0);
  for (std::size_t v = 0; v < g.voxel_count(); ++v) {
    const float p = em.posterior[0][v], vent = em.posterior[1][v], out = em.posterior[2][v];
    brain.voxels[v] = std::max(p, vent) > out;
    ventricle.voxels[v] = vent > p && vent > out;
  }
  keep_carried_ventricles(brain, ventricle, ventricle_box);
  clean_brain(brain, em.posterior, ventricle, params.max_filled_hole_ml);

  IntraopSegmentation result;
  result.labels = LabelImage(image.grid, 0);
  result.confidence = ImageF(image.grid, 1.f);
  result.bias = ImageF(image.grid, 1.f);
  const std::uint16_t ventricle_value = ventricle_labels.empty() ? brain_label : ventricle_labels.front();
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const std::size_t v = g.index(i, j, k);
        const std::size_t w = image.grid.index(i + box.lo[0], j + box.lo[1], k + box.lo[2]);
        const int chosen = ventricle.voxels[v] ? 1 : brain.voxels[v] ? 0 : 2;
        result.labels.voxels[w] = chosen == 1 ? ventricle_value : chosen == 0 ? brain_label : 0;
        result.confidence.voxels[w] = em.posterior[chosen][v];
        result.bias.voxels[w] = em.bias[v];
      }
  result.classes = em.classes;
  result.report = describe(em);
  const double class_contrast = fluid_contrast_sd(em.classes);
  result.report["fluid_contrast_sd"] = std::isfinite(class_contrast) ? class_contrast : -1.0;
  const double wall_contrast = ventricle_wall_contrast_sd(image_box, em.bias, ventricle, brain);
  result.report["ventricle_wall_contrast_sd"] = std::isfinite(wall_contrast) ? wall_contrast : -1.0;
  const double contrast = std::min(class_contrast, wall_contrast);
  result.report["prior_width_mm"] = params.prior_width_mm;
  result.report["ventricle_prior_width_mm"] = params.ventricle_prior_width_mm;
  result.report["ventricle_shift_mm"] = params.ventricle_shift_mm;
  result.report["prior_inward_width_mm"] = widths.inward_mm;
  result.report["brain_ml"] = volume_ml(brain);
  result.report["ventricles_ml"] = volume_ml(ventricle);
  if (std::isfinite(contrast) && contrast < params.min_fluid_contrast_sd)
    result.refusal = "the image does not separate ventricular fluid from brain tissue (" +
                     std::to_string(contrast) + " sd apart, at least " +
                     std::to_string(params.min_fluid_contrast_sd) + " needed): not an MR contrast the "
                     "automatic segmentation can use; fitted classes " + result.report["classes"].dump();
  else if (count_nonzero(brain) == 0)
    result.refusal = "no brain tissue was found in the image";
  return result;
}

}  // namespace brainshift::segmentation
