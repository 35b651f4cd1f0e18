#include "segmentation/label_image_check.h"

#include <cmath>
#include <cstdio>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/image_stats.h"
#include "image/resample.h"
#include "registration/boundary_samples.h"

namespace brainshift::segmentation {
Disagreement disagreement_beyond_band(const Mask& a, const Mask& b, const ImageF& confidence, double min_posterior,
                                      double band_mm) {
  const ImageF distance_from_b_mm = distance_to_mask_mm(b);
  Disagreement d;
  Mask m(a.grid, 0);
  for (std::size_t v = 0; v < a.voxels.size(); ++v)
    m.voxels[v] = a.voxels[v] && !b.voxels[v] && confidence.voxels[v] >= min_posterior &&
                  distance_from_b_mm.voxels[v] > band_mm;
  d.volume_ml = volume_ml(m);
  if (d.volume_ml <= 0) return d;
  for (std::size_t v = 0; v < m.voxels.size(); ++v)
    if (m.voxels[v]) d.max_depth_mm = std::max<double>(d.max_depth_mm, distance_from_b_mm.voxels[v]);
  const Eigen::Vector3d c = centroid_mm(m);
  d.centroid_mm = {c.x(), c.y(), c.z()};
  return d;
}

std::string to_text(const Disagreement& d, double band_mm) {
  char text[200];
  std::snprintf(text, sizeof text, "%.1f ml beyond %.0f mm, up to %.0f mm deep, centred at (%.0f, %.0f, %.0f) mm RAS",
                d.volume_ml, band_mm, d.max_depth_mm, d.centroid_mm[0], d.centroid_mm[1], d.centroid_mm[2]);
  return text;
}

nlohmann::json to_json(const Disagreement& d) {
  return {{"volume_ml", d.volume_ml}, {"max_depth_mm", d.max_depth_mm}, {"centroid_mm", d.centroid_mm}};
}

LabelImageCheck check_labels_against_image(const ImageF& full_image, const LabelImage& full_labels,
                                           std::uint16_t brain_label,
                                           const std::vector<std::uint16_t>& ventricle_labels,
                                           const LabelImageCheckParameters& params) {
  if (!full_image.grid.same_geometry(full_labels.grid))
    throw InputError("label check: the image and the labels are on different grids");
  // The working grid's rule (image/resample.h): the same extent, whole
  // voxels. The image trilinearly: at a ratio of 2 a coarse centre lies
  // midway between fine ones and averages their noise down. The labels by
  // cover (downsample_labels): the nearest voxel to a centre midway between
  // two rounds the half one way and moved the given outline by half a
  // voxel per axis before it was compared.
  const Grid3 grid = working_grid(full_image.grid, params.grid_spacing_mm);
  const bool coarse = grid.dims != full_image.grid.dims;
  const ImageF image = coarse ? resample_linear(full_image, grid) : full_image;
  const LabelImage labels = coarse ? downsample_labels(full_labels, grid) : full_labels;
  SegmentationParameters sp = params.classifier;
  sp.prior_width_mm = params.prior_width_mm;
  sp.em.fit_samples = params.fit_samples;
  // Only the outline is compared: how well the image shows the ventricles
  // does not matter here.
  sp.min_fluid_contrast_sd = 0;
  // The open-fluid rule (intraop_segmentation.h) edits the outline by its
  // shape, for the image-only path's gap under a sunken cortex. The check
  // asks what the image's intensities show: a leak into that gap is fluid
  // by intensity and is found without the rule, and with it a T2-like image
  // (bright sulcal fluid) had 40 ml of true brain called fluid, a false
  // refusal (hospital suite atlas_midline6_T2_oblique25).
  sp.max_sulcus_half_width_mm = 0;
  const IntraopSegmentation seg = segment_intraop(image, labels, brain_label, ventricle_labels, sp);
  const Mask given = outline_mask(labels);
  const Mask seen = outline_mask(seg.labels);
  LabelImageCheck check;
  check.brain_ml = volume_ml(given);
  if (!seg.refusal.empty()) {  // the image cannot be classified: nothing to check against
    check.metrics = {{"checked", false}, {"why", seg.refusal}};
    return check;
  }
  check.labels_not_image = disagreement_beyond_band(given, seen, seg.confidence, params.min_posterior, params.band_mm);
  check.image_not_labels = disagreement_beyond_band(seen, given, seg.confidence, params.min_posterior, params.band_mm);
  const double limit_ml = params.max_disagreement_fraction * check.brain_ml;
  auto describe = [&](const Disagreement& d, const char* what) {
    return std::string(what) + ": " + to_text(d, params.band_mm);
  };
  if (check.labels_not_image.volume_ml > limit_ml)
    check.failure = describe(check.labels_not_image,
                             "the intraop labels call brain what the image shows as fluid, dura or air");
  else if (check.image_not_labels.volume_ml > limit_ml)
    check.failure = describe(check.image_not_labels, "the image shows brain the intraop labels lack");
  check.metrics = {{"checked", true},
                   {"labels_not_image", to_json(check.labels_not_image)},
                   {"image_not_labels", to_json(check.image_not_labels)},
                   {"brain_ml", check.brain_ml},
                   {"limit_ml", limit_ml},
                   {"band_mm", params.band_mm},
                   {"grid_spacing_mm", {grid.spacing_mm().x(), grid.spacing_mm().y(), grid.spacing_mm().z()}},
                   {"passed", check.failure.empty()}};
  if (!check.failure.empty()) check.metrics["failure"] = check.failure;
  return check;
}

}  // namespace brainshift::segmentation
