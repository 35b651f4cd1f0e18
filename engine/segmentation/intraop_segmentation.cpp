#include "segmentation/intraop_segmentation.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "registration/boundary_samples.h"
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

// The classes fitted on the box, first under the shading found from the
// histogram when that is on (sharpening_bias.h): the classes and their
// polynomial see the image corrected by it, every use of the bias after them
// the product. The product is no polynomial: bias_field is left empty, and a
// later round that reuses the fit reuses the bias image (earlier_log_bias).
// The sharpening's report in `report` (null when off).
EmResult fit_classes(const ImageF& image_box, const TissuePrior& prior, const Mask& outline_box,
                     const SegmentationParameters& params, const EmParameters& em_params, nlohmann::json& report) {
  if (!params.sharpening_bias) return fit_tissue_mixture(image_box, prior, em_params);
  const Stopwatch watch;
  const SharpeningBias sharpening = sharpening_log_bias(image_box, outline_box, params.sharpening);
  report = to_json(sharpening);
  report["seconds"] = watch.seconds();
  if (sharpening.iterations == 0 || sharpening.discarded) return fit_tissue_mixture(image_box, prior, em_params);
  ImageF flattened = image_box;
  for (std::size_t v = 0; v < flattened.voxels.size(); ++v)
    flattened.voxels[v] = static_cast<float>(flattened.voxels[v] * std::exp(-sharpening.log_bias[v]));
  EmResult em = fit_tissue_mixture(flattened, prior, em_params);
  for (std::size_t v = 0; v < em.bias.size(); ++v)
    em.bias[v] = static_cast<float>(em.bias[v] * std::exp(sharpening.log_bias[v]));
  em.bias_field.reset();
  return em;
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
  nlohmann::json sharpening_report;
  const EmResult em = fitted ? classify_with_classes(image_box, prior, fitted->classes,
                                                     earlier_log_bias(*fitted, box, g), em_params)
                             : fit_classes(image_box, prior, outline_box, params, em_params, sharpening_report);

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
  if (!sharpening_report.is_null()) result.report["sharpening_bias"] = std::move(sharpening_report);
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
