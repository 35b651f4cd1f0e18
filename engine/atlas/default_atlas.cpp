#include "atlas/default_atlas.h"

#include <nlohmann/json.hpp>

#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <fstream>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/label_colour.h"
#include "image/image_stats.h"
#include "image/morphology.h"
#include "image/nifti_io.h"
#include "image/resample.h"

namespace brainshift {
namespace {

// Bump when the method changes so that old caches are rebuilt.
constexpr int kAtlasVersion = 1;

// JHU-WhiteMatter-labels-1mm values that make up the corticospinal tract.
const std::vector<std::uint16_t> kJhuCstLabels{7, 8, 15, 16, 19, 20, 25, 26};

// Brings an image onto the reference grid through world coordinates; a no-op
// copy when the grids already coincide.
ImageF on_grid(const ImageF& img, const Grid3& ref) {
  return img.grid.same_geometry(ref) ? img : resample_linear(img, ref);
}

Mask and_mask(const Mask& a, const Mask& b) {
  Mask out(a.grid, 0);
  for (std::size_t i = 0; i < out.voxels.size(); ++i) out.voxels[i] = a.voxels[i] && b.voxels[i];
  return out;
}

Mask brain_mask(const ImageF& bet_on_t1) {
  Mask m = threshold(bet_on_t1, 1e-3f, std::numeric_limits<float>::max());
  m = fill_holes(largest_component(m, 6));
  // close 2 mm bridges one-voxel notches; open 1 mm drops one-voxel strands.
  m = open(close(m, 2.0), 1.0);
  return fill_holes(largest_component(m, 6));
}

struct VentricleParams {
  float better_csf_max = 30.f;  // ch2better has CSF set to 0; partial volume after resampling
  float t1_csf_max = 60.f;      // CSF ~30, grey matter ~80, white matter ~110 in ch2
  double brain_erosion_mm = 3.0;
  double min_component_ml = 0.5;
};

// Keeps CSF components whose centroid lies in the central box where the
// bodies of the lateral ventricles are (MNI-like ch2 coordinates, mm).
bool central(const Eigen::Vector3d& c) {
  return std::abs(c.x()) < 30.0 && c.y() > -45.0 && c.y() < 35.0 && c.z() > 0.0 && c.z() < 40.0;
}

Mask ventricle_mask(const ImageF& t1, const ImageF& better_on_t1, const Mask& brain, const VentricleParams& p) {
  const Mask deep = erode(brain, p.brain_erosion_mm);
  Mask csf(t1.grid, 0);
  for (std::size_t i = 0; i < csf.voxels.size(); ++i)
    csf.voxels[i] = deep.voxels[i] && better_on_t1.voxels[i] < p.better_csf_max && t1.voxels[i] < p.t1_csf_max;
  int n = 0;
  const auto comp = connected_components(csf, 6, &n);
  std::vector<std::size_t> count(n + 1, 0);
  std::vector<Eigen::Vector3d> sum(n + 1, Eigen::Vector3d::Zero());
  const Grid3& g = t1.grid;
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i) {
        const int c = comp.voxels[g.index(i, j, k)];
        if (c == 0) continue;
        ++count[c];
        sum[c] += g.world_mm(i, j, k);
      }
  const double voxel_ml = std::abs(g.world_from_voxel.topLeftCorner<3, 3>().determinant()) / 1000.0;
  std::vector<std::uint8_t> keep(n + 1, 0);
  for (int c = 1; c <= n; ++c)
    keep[c] = count[c] * voxel_ml >= p.min_component_ml && central(sum[c] / count[c]);
  Mask v(g, 0);
  for (std::size_t i = 0; i < v.voxels.size(); ++i) v.voxels[i] = keep[comp.voxels[i]];
  return and_mask(close(v, 1.0), brain);
}

}  // namespace

DefaultAtlas build_default_atlas(const std::filesystem::path& dir) {
  DefaultAtlas atlas;
  atlas.t1 = read_scalar_image(dir / "ch2.nii.gz");
  const Grid3& grid = atlas.t1.grid;
  const Mask brain = brain_mask(on_grid(read_scalar_image(dir / "ch2bet.nii.gz"), grid));
  const ImageF better = on_grid(read_scalar_image(dir / "ch2better.nii.gz"), grid);
  const Mask ventricles = ventricle_mask(atlas.t1, better, brain, VentricleParams{});
  atlas.labels = compose_atlas_labels(brain, ventricles, jhu_corticospinal_tract(dir, grid));
  return atlas;
}

Mask jhu_corticospinal_tract(const std::filesystem::path& dir, const Grid3& grid) {
  const LabelImage jhu_src = read_label_image(dir / "JHU-WhiteMatter-labels-1mm.nii.gz");
  const LabelImage jhu = jhu_src.grid.same_geometry(grid) ? jhu_src : resample_nearest(jhu_src, grid);
  return mask_of_labels(jhu, kJhuCstLabels);
}

LabelImage compose_atlas_labels(const Mask& brain, const Mask& ventricles, const Mask& cst) {
  LabelImage labels(brain.grid, atlas_labels::background);
  for (std::size_t i = 0; i < labels.voxels.size(); ++i) {
    if (!brain.voxels[i]) continue;
    labels.voxels[i] = ventricles.voxels[i] ? atlas_labels::ventricles
                       : cst.voxels[i]      ? atlas_labels::corticospinal_tract
                                            : atlas_labels::brain;
  }
  return labels;
}

namespace {

struct CachePaths {
  std::filesystem::path t1, labels, provenance;
};

CachePaths cache_paths(const std::filesystem::path& dir) {
  return {dir / "t1.nii.gz", dir / "labels.nii.gz", dir / "provenance.json"};
}

// Throws on anything unexpected; the caller then rebuilds.
DefaultAtlas load_cache(const CachePaths& paths) {
  std::ifstream in(paths.provenance);
  if (!in) throw InputError(paths.provenance.string() + ": missing");
  const nlohmann::json prov = nlohmann::json::parse(in);
  if (prov.at("version").get<int>() != kAtlasVersion)
    throw InputError(paths.provenance.string() + ": atlas version differs");
  DefaultAtlas atlas{read_scalar_image(paths.t1), read_label_image(paths.labels)};
  if (!atlas.t1.grid.same_geometry(atlas.labels.grid))
    throw InputError(paths.labels.string() + ": grid differs from " + paths.t1.string());
  for (std::uint16_t v : atlas.labels.voxels)
    if (v > atlas_labels::corticospinal_tract) throw InputError(paths.labels.string() + ": unexpected label value");
  return atlas;
}

nlohmann::json provenance(const DefaultAtlas& atlas, const std::filesystem::path& templates_dir) {
  nlohmann::json j;
  j["version"] = kAtlasVersion;
  j["templates_dir"] = templates_dir.string();
  j["sources"] = {"ch2.nii.gz", "ch2bet.nii.gz", "ch2better.nii.gz", "JHU-WhiteMatter-labels-1mm.nii.gz"};
  j["labels"] = {{"1", "brain parenchyma"}, {"2", "lateral ventricles"}, {"3", "corticospinal tract"}};
  j["jhu_cst_labels"] = kJhuCstLabels;
  for (std::uint16_t l : {atlas_labels::brain, atlas_labels::ventricles, atlas_labels::corticospinal_tract})
    j["volume_ml"][std::to_string(l)] = volume_ml(mask_of_labels(atlas.labels, {l}));
  return j;
}

// Each file is written under a temporary name and renamed, and the provenance
// goes last, so an interrupted build never leaves a cache that looks complete.
void write_cache(const DefaultAtlas& atlas, const CachePaths& paths, const std::filesystem::path& templates_dir) {
  std::filesystem::create_directories(paths.t1.parent_path());
  std::filesystem::remove(paths.provenance);
  const auto tmp = [](const std::filesystem::path& p) { // pid: two processes building at once must not write the same file.
    return p.parent_path() / ("tmp" + std::to_string(::getpid()) + "_" + p.filename().string());
  };
  write_scalar_image(tmp(paths.t1), atlas.t1, VoxelType::float32);
  write_label_image(tmp(paths.labels), atlas.labels);
  std::filesystem::rename(tmp(paths.t1), paths.t1);
  std::filesystem::rename(tmp(paths.labels), paths.labels);
  {
    std::ofstream out(tmp(paths.provenance));
    out << provenance(atlas, templates_dir).dump(2) << "\n";
    if (!out) throw InputError(paths.provenance.string() + ": cannot write");
  }
  std::filesystem::rename(tmp(paths.provenance), paths.provenance);
}

}  // namespace

DefaultAtlas load_or_build_default_atlas(const std::filesystem::path& cache_dir,
                                         const std::filesystem::path& templates_dir) {
  const CachePaths paths = cache_paths(cache_dir);
  try {
    return load_cache(paths);
  } catch (const std::exception&) {
    // Missing or corrupt cache: rebuild below (the sources are authoritative).
  }
  DefaultAtlas atlas = build_default_atlas(templates_dir);
  write_cache(atlas, paths, templates_dir);
  return atlas;
}

LabelImage atlas_labels_for(const LabelImage& atlas, const LabelTable& table) {
  const std::uint16_t parenchyma = table.brain_label();
  auto value_for = [&](const char* name) {
    const LabelEntry* e = table.find(std::string(name));
    return e ? e->value : parenchyma;
  };
  std::array<std::uint16_t, 4> to{atlas_labels::background, parenchyma, value_for("ventricles"),
                                  value_for("corticospinal_tract")};
  LabelImage out = atlas;
  for (auto& v : out.voxels) v = v < to.size() ? to[v] : parenchyma;
  return out;
}

}  // namespace brainshift
