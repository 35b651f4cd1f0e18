#include "segmentation/tissue_prior.h"

#include <cmath>

#include "core/errors.h"
#include "core/parallel.h"
#include "image/distance_map.h"
#include "image/image_stats.h"

namespace brainshift::segmentation {

const char* name_of(Tissue t) {
  switch (t) {
    case Tissue::parenchyma: return "parenchyma";
    case Tissue::ventricle: return "ventricle";
    case Tissue::outside: return "outside";
  }
  return "?";
}

namespace {

// Logistic of -d / w, written so that infinite distances (an empty mask) give
// exactly 0 or 1.
float inside_probability(float signed_distance_mm, double width_mm) {
  if (std::isinf(signed_distance_mm)) return signed_distance_mm < 0 ? 1.f : 0.f;
  return static_cast<float>(1.0 / (1.0 + std::exp(signed_distance_mm / width_mm)));
}

}  // namespace

double prior_reach_mm(double outline_mm, double floor) {
  if (!(outline_mm > 0) || !(floor > 0 && floor < 0.25))
    throw InputError("tissue prior: the reach needs a width > 0 and a floor in (0, 0.25)");
  return outline_mm * std::log((1 - 3 * floor) / floor);
}

TissuePrior tissue_prior(const Mask& outline, const Mask& ventricles, const PriorWidths& widths, double floor) {
  if (!(widths.ventricle_shift_mm >= 0)) throw InputError("tissue prior: the ventricles' shift must be >= 0");
  if (!(widths.outline_mm > 0) || !(widths.inward_mm > 0) || !(widths.ventricle_mm > 0))
    throw InputError("tissue prior: the widths must be positive");
  if (!(floor >= 0 && floor <= 0.1)) throw InputError("tissue prior: the floor must be in [0, 0.1]");
  if (count_nonzero(outline) == 0) throw InputError("tissue prior: the carried brain outline is empty");
  const ImageF d_outline = signed_distance_mm(outline);
  const ImageF d_ventricle = signed_distance_mm(ventricles);
  TissuePrior prior;
  prior.grid = outline.grid;
  prior.ventricle_share = static_cast<double>(count_nonzero(ventricles)) / static_cast<double>(count_nonzero(outline));
  const std::size_t n = outline.grid.voxel_count();
  for (auto& p : prior.p) p.resize(n);
  // The floor is for parenchyma and outside only: ventricles do not appear
  // far from where they were (they move and swell by millimetres, which the
  // logistic's tail covers), while fluid outside the brain looks exactly like
  // them.
  const float keep = static_cast<float>(1.0 - 2 * floor), f = static_cast<float>(floor);
  parallel_halves(n, 1 << 16, [&](std::size_t begin, std::size_t end) {  // each voxel on its own
  for (std::size_t v = begin; v < end; ++v) {
    const float d = d_outline.voxels[v];
    const float in = inside_probability(d, d < 0 ? widths.inward_mm : widths.outline_mm);
    const float vent =
        widths.ventricle_shift_mm > 0
            ? 0.5f * inside_probability(d_ventricle.voxels[v] - static_cast<float>(widths.ventricle_shift_mm),
                                        widths.ventricle_mm)
            : inside_probability(d_ventricle.voxels[v], widths.ventricle_mm);
    prior.p[0][v] = f + keep * in * (1 - vent);
    prior.p[1][v] = keep * in * vent;
    prior.p[2][v] = f + keep * (1 - in);
  }
  });
  return prior;
}

}  // namespace brainshift::segmentation
