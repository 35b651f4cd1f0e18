#include "head_shapes.h"

#include <algorithm>
#include <cmath>
#include <random>

#include "core/errors.h"
#include "image/distance_map.h"
#include "image/morphology.h"
#include "image/resample.h"

namespace brainshift::test {
namespace {

constexpr double kPi = 3.14159265358979323846;

// out(x) = labels(source(x)) at every voxel centre x (nearest neighbour).
template <typename SourceFn>
LabelImage pull_back(const LabelImage& labels, SourceFn source) {
  LabelImage out(labels.grid, 0);
  const GridSampler sampler(labels.grid);
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        out.at(i, j, k) = sampler.nearest(labels.voxels, source(labels.grid.world_mm(i, j, k)), 0);
  return out;
}

// Paints `label` on the tissue voxels (non-zero) within radius_mm of centre_mm.
void paint_ball_in_tissue(LabelImage& labels, const Eigen::Vector3d& centre_mm, double radius_mm,
                          std::uint16_t label) {
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (labels.at(i, j, k) != 0 && (labels.grid.world_mm(i, j, k) - centre_mm).norm() <= radius_mm)
          labels.at(i, j, k) = label;
}

}  // namespace

HeadLabels head_labels_of(const LabelTable& table) {
  HeadLabels l;
  l.brain = table.brain_label();
  const auto cavities = table.cavity_labels();
  const auto resectable = table.resectable_labels();
  if (cavities.empty() || resectable.empty())
    throw InputError("head_labels_of: the label table needs a cavity and a resectable label");
  l.ventricles = cavities.front();
  l.tumour = resectable.front();
  return l;
}

Eigen::Vector3d label_centroid_mm(const LabelImage& labels, std::uint16_t label) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  std::size_t n = 0;
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (labels.at(i, j, k) == label) sum += labels.grid.world_mm(i, j, k), ++n;
  if (n == 0) throw InputError("label_centroid_mm: no voxel has label " + std::to_string(label));
  return sum / static_cast<double>(n);
}

LabelImage reshape_head(const LabelImage& labels, const HeadLabels& l, const Eigen::Vector3d& scale,
                        double bump_mm, unsigned seed) {
  const Eigen::Vector3d c = label_centroid_mm(labels, l.brain);
  std::mt19937 rng(seed);
  Eigen::Vector3d phase;
  for (int a = 0; a < 3; ++a) phase[a] = 2 * kPi * static_cast<double>(rng() % 1000) / 1000.0;
  return pull_back(labels, [&](const Eigen::Vector3d& x) {
    const Eigen::Vector3d r = x - c;
    Eigen::Vector3d bump;
    for (int a = 0; a < 3; ++a) bump[a] = bump_mm * std::sin(2 * kPi * r[(a + 1) % 3] / 120.0 + phase[a]);
    return Eigen::Vector3d(c + r.cwiseQuotient(scale) - bump);
  });
}

LabelImage enlarge_ventricles(const LabelImage& labels, const HeadLabels& l, double volume_factor) {
  const ImageF distance = distance_to_mask_mm(mask_of_labels(labels, {l.ventricles}));
  std::size_t original = 0;
  std::vector<std::pair<float, std::size_t>> candidates;  // (distance, voxel): ties broken by index
  for (std::size_t v = 0; v < labels.voxels.size(); ++v) {
    if (labels.voxels[v] == l.ventricles) ++original;
    else if (labels.voxels[v] != 0) candidates.emplace_back(distance.voxels[v], v);
  }
  const auto extra = static_cast<std::size_t>(std::ceil((volume_factor - 1.0) * static_cast<double>(original)));
  if (original == 0 || extra == 0 || extra > candidates.size())
    throw InputError("enlarge_ventricles: no ventricles, or the factor is out of reach");
  std::nth_element(candidates.begin(), candidates.begin() + static_cast<std::ptrdiff_t>(extra - 1), candidates.end());
  LabelImage out = labels;
  for (std::size_t c = 0; c < extra; ++c) out.voxels[candidates[c].second] = l.ventricles;
  return out;
}

LabelImage collapse_ventricles_near(const LabelImage& labels, const HeadLabels& l, const Eigen::Vector3d& centre_mm,
                                    double lost_fraction) {
  std::vector<std::pair<double, std::size_t>> ventricle;  // (distance to centre, voxel)
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (labels.at(i, j, k) == l.ventricles)
          ventricle.emplace_back((labels.grid.world_mm(i, j, k) - centre_mm).norm(), labels.grid.index(i, j, k));
  const auto lost = static_cast<std::size_t>(lost_fraction * static_cast<double>(ventricle.size()));
  LabelImage out = labels;
  if (lost == 0) return out;
  std::nth_element(ventricle.begin(), ventricle.begin() + static_cast<std::ptrdiff_t>(lost - 1), ventricle.end());
  for (std::size_t c = 0; c < lost; ++c) out.voxels[ventricle[c].second] = l.brain;
  return out;
}

LabelImage add_tumour_with_mass_effect(const LabelImage& labels, const HeadLabels& l,
                                       const Eigen::Vector3d& centre_mm, double radius_mm) {
  const double r3 = radius_mm * radius_mm * radius_mm;
  LabelImage out = pull_back(labels, [&](const Eigen::Vector3d& x) {
    const Eigen::Vector3d r = x - centre_mm;
    const double rho = r.norm();
    if (rho <= radius_mm) return centre_mm;  // painted below
    return Eigen::Vector3d(centre_mm + r * (std::cbrt(rho * rho * rho - r3) / rho));
  });
  paint_ball_in_tissue(out, centre_mm, radius_mm, l.tumour);
  return out;
}

Eigen::Vector3d point_at_distance_from_label(const LabelImage& labels, std::uint16_t label,
                                             const Eigen::Vector3d& from_mm, const Eigen::Vector3d& direction,
                                             double distance_mm) {
  const ImageF distance = distance_to_mask_mm(mask_of_labels(labels, {label}));
  const Eigen::Vector3d step = direction.normalized() * 0.5;
  const bool start_below = sample_linear(distance, from_mm, 1e9f) < distance_mm;
  for (int s = 1; s <= 300; ++s) {
    const Eigen::Vector3d p = from_mm + s * step;
    if ((sample_linear(distance, p, 1e9f) < distance_mm) != start_below) return p;
  }
  throw InputError("point_at_distance_from_label: distance never reached along the ray");
}

LabelImage add_specks(const LabelImage& labels, const HeadLabels& l, int count, unsigned seed) {
  std::array<int, 3> lo = labels.grid.dims, hi{0, 0, 0};
  const auto& d = labels.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (labels.at(i, j, k) != 0) {
          const int ijk[3] = {i, j, k};
          for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], ijk[a]), hi[a] = std::max(hi[a], ijk[a]);
        }
  LabelImage out = labels;
  std::mt19937 rng(seed);
  int made = 0;
  for (int attempt = 0; attempt < 100 * count && made < count; ++attempt) {
    int ijk[3];
    for (int a = 0; a < 3; ++a) ijk[a] = lo[a] + static_cast<int>(rng() % static_cast<unsigned>(hi[a] - lo[a] + 1));
    const int kind = made % 3;
    const std::uint16_t here = out.at(ijk[0], ijk[1], ijk[2]);
    const bool fits = (kind == 0 && here == 0) || (kind == 1 && here == l.brain) || (kind == 2 && here != 0);
    if (!fits) continue;
    const std::uint16_t paint = kind == 0 ? l.brain : kind == 1 ? l.ventricles : l.tumour;
    out.at(ijk[0], ijk[1], ijk[2]) = paint;
    // Every other speck is two voxels (a one-voxel speck and a pair).
    if (made % 2 == 1 && ijk[0] + 1 < d[0] && out.at(ijk[0] + 1, ijk[1], ijk[2]) == here)
      out.at(ijk[0] + 1, ijk[1], ijk[2]) = paint;
    ++made;
  }
  return out;
}

namespace {

// Issue 17's runaway kind, drawn from a seed: proportions 0.9-1.1 per axis,
// a 3-6 mm reshaping, a 12-20 mm tumour 2 mm lateral (left or right) of the
// ventricles compressing them; odd seeds keep the tumour label, even seeds
// paint it as brain (a map that does not label the tumour).
// rescale_voxels: the proportions are given to the voxels instead (the same
// label array on voxels of 0.9-1.1 mm per axis), then a 2 mm smooth reshaping.
LabelImage searched_head(const LabelImage& atlas, const HeadLabels& l, unsigned seed, bool rescale_voxels = false) {
  std::mt19937 rng(seed);
  auto uniform = [&](double lo, double hi) { return lo + (hi - lo) * static_cast<double>(rng() % 10001) / 10000.0; };
  const Eigen::Vector3d scale(uniform(0.9, 1.1), uniform(0.9, 1.1), uniform(0.9, 1.1));
  const double bump = uniform(3, 6), radius = uniform(12, 20);
  const Eigen::Vector3d lateral((rng() % 2) ? 1.0 : -1.0, 0, 0);
  LabelImage head;
  if (rescale_voxels) {
    LabelImage scaled = atlas;
    const Eigen::Vector3d c = label_centroid_mm(atlas, l.brain);
    scaled.grid.world_from_voxel.topLeftCorner<3, 3>() = scale.asDiagonal() * atlas.grid.world_from_voxel.topLeftCorner<3, 3>();
    scaled.grid.world_from_voxel.topRightCorner<3, 1>() =
        c + scale.asDiagonal() * (atlas.grid.world_from_voxel.topRightCorner<3, 1>() - c);
    head = reshape_head(scaled, l, Eigen::Vector3d::Ones(), 2.0, seed);
  } else {
    head = reshape_head(atlas, l, scale, bump, seed);
  }
  const Eigen::Vector3d c = point_at_distance_from_label(head, l.ventricles, label_centroid_mm(head, l.ventricles),
                                                         lateral, radius + 2.0);
  LabelImage out = collapse_ventricles_near(add_tumour_with_mass_effect(head, l, c, radius), l, c, 0.4);
  if (seed % 2 == 0)
    for (auto& v : out.voxels)
      if (v == l.tumour) v = l.brain;
  return out;
}

}  // namespace

std::vector<std::string> head_case_names() {
  return {"atlas",           "enlarged_ventricles_x1.8", "enlarged_ventricles_x2.4",
          "compressed_ventricles", "reshaped",           "reshaped_compressed",
          "tumour_at_ventricle_wall", "tumour_at_surface", "specks"};
}

// Sizes: a 15 mm tumour 2 mm from the ventricle pushes its near wall ~5.5 mm
// and its far wall (~10 mm on) ~1.6 mm, and the 40 % of the ventricles
// nearest to it collapse (CSF is pressed out; tissue is not). Proportions 0.9-1.1 per axis with a 4-5 mm reshaping are those
// of the independent cases that once made the mesher run away.
HeadCase make_head_case(const std::string& name, const LabelImage& atlas, const HeadLabels& l) {
  const Eigen::Vector3d lateral(1, 0, 0);
  auto compressed = [&](const LabelImage& head) {
    const Eigen::Vector3d c = point_at_distance_from_label(head, l.ventricles, label_centroid_mm(head, l.ventricles),
                                                           lateral, 15.0 + 2.0);
    return collapse_ventricles_near(add_tumour_with_mass_effect(head, l, c, 15.0), l, c, 0.4);
  };
  if (name == "atlas") return {name, atlas};
  if (name == "enlarged_ventricles_x1.8") return {name, enlarge_ventricles(atlas, l, 1.8)};
  if (name == "enlarged_ventricles_x2.4") return {name, enlarge_ventricles(atlas, l, 2.4)};
  if (name == "compressed_ventricles") return {name, compressed(atlas)};
  if (name == "reshaped") return {name, reshape_head(atlas, l, {1.08, 0.92, 1.05}, 4.0, 1)};
  if (name == "reshaped_compressed") return {name, compressed(reshape_head(atlas, l, {0.9, 1.1, 0.95}, 5.0, 2))};
  if (name == "tumour_at_ventricle_wall") {
    LabelImage out = atlas;
    const Eigen::Vector3d c = point_at_distance_from_label(atlas, l.ventricles, label_centroid_mm(atlas, l.ventricles),
                                                           lateral, 10.0 - 1.0);
    paint_ball_in_tissue(out, c, 10.0, l.tumour);
    return {name, out};
  }
  if (name == "tumour_at_surface") {
    LabelImage out = atlas;
    const Eigen::Vector3d c = point_at_distance_from_label(atlas, 0, label_centroid_mm(atlas, l.brain),
                                                           Eigen::Vector3d(1, 0.4, 0.6), 12.0 - 1.0);
    paint_ball_in_tissue(out, c, 12.0, l.tumour);
    return {name, out};
  }
  if (name == "specks") return {name, add_specks(atlas, l, 300, 7)};
  if (name.rfind("search_voxels_", 0) == 0)
    return {name, searched_head(atlas, l, static_cast<unsigned>(std::stoul(name.substr(14))), true)};
  if (name.rfind("search_", 0) == 0) return {name, searched_head(atlas, l, static_cast<unsigned>(std::stoul(name.substr(7))))};
  throw InputError("make_head_case: unknown case " + name);
}

}  // namespace brainshift::test
