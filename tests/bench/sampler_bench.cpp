// Speed of the trilinear sampler (image/trilinear.h) on the per-scan paths
// that use it: resampling an image, warping one with a pull-back field, the
// registration's value-and-gradient sampler on a distance map and the
// vector-field sampler. Fixed-seed synthetic inputs of the intraop size; the
// fastest of --repeat runs (the VM is shared), and a checksum of the outputs
// so that two builds can be compared for the same answer. JSON on stdout.
//   brainshift_sampler_bench [--repeat N] [--points N]
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>

#include <nlohmann/json.hpp>

#include "core/timer.h"
#include "field/field_fill.h"
#include "field/vector_sampling.h"
#include "field/warp.h"
#include "image/resample.h"
#include "registration/linear_sampler.h"

using namespace brainshift;

namespace {

Grid3 grid(int n, double spacing_mm, const Eigen::Vector3d& origin_mm) {
  Grid3 g;
  g.dims = {n, n, n};
  g.world_from_voxel.topLeftCorner<3, 3>() = spacing_mm * Eigen::Matrix3d::Identity();
  g.world_from_voxel.topRightCorner<3, 1>() = origin_mm;
  return g;
}

ImageF random_image(const Grid3& g, std::mt19937_64& rng) {
  std::uniform_real_distribution<float> value(0.f, 1000.f);
  ImageF img(g);
  for (auto& v : img.voxels) v = value(rng);
  return img;
}

// A smooth field of a few mm, so that the warp reads nearby voxels as a real one does.
VectorImage3 smooth_field(const Grid3& g) {
  VectorImage3 u(g);
  for (int k = 0; k < g.dims[2]; ++k)
    for (int j = 0; j < g.dims[1]; ++j)
      for (int i = 0; i < g.dims[0]; ++i)
        u.vectors[g.index(i, j, k)] = Eigen::Vector3f(3.f * std::sin(0.05f * j), 2.f * std::cos(0.04f * k),
                                                      1.5f * std::sin(0.03f * i + 0.02f * k));
  return u;
}

template <class Fn>
double fastest(int repeat, Fn&& fn) {
  double best = std::numeric_limits<double>::infinity();
  for (int r = 0; r < repeat; ++r) {
    Stopwatch clock;
    fn();
    best = std::min(best, clock.seconds());
  }
  return best;
}

double sum(const std::vector<float>& v) {
  double s = 0;
  for (float x : v) s += x;
  return s;
}

}  // namespace

int main(int argc, char** argv) {
  int repeat = 5, points = 4000000;
  CLI::App app("trilinear sampler benchmark: seconds per call on the per-scan paths");
  app.add_option("--repeat", repeat, "runs per measurement; the fastest is reported");
  app.add_option("--points", points, "random points for the point samplers");
  CLI11_PARSE(app, argc, argv);

  std::mt19937_64 rng(7);
  // Preop 1 mm, intraop 1.2 mm, offset so that part of the target falls outside.
  const ImageF preop = random_image(grid(180, 1.0, {-90, -90, -90}), rng);
  const Grid3 target = grid(160, 1.2, {-100, -92, -88});
  const VectorImage3 u = smooth_field(target);
  Eigen::Matrix4d rotate = Eigen::Matrix4d::Identity();
  rotate.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.1, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();

  std::vector<Eigen::Vector3d> world(static_cast<std::size_t>(points)), voxel(world.size());
  std::uniform_real_distribution<double> coord(-95, 95), index(-1, 160);
  for (std::size_t n = 0; n < world.size(); ++n) {
    world[n] = {coord(rng), coord(rng), coord(rng)};
    voxel[n] = {index(rng), index(rng), index(rng)};
  }

  nlohmann::json out;
  double check = 0;
  out["resample_linear_s"] = fastest(repeat, [&] { check = sum(resample_linear(preop, target, rotate).voxels); });
  out["resample_linear_checksum"] = check;
  out["warp_image_linear_s"] = fastest(repeat, [&] { check = sum(warp_image_linear(preop, u).voxels); });
  out["warp_image_linear_checksum"] = check;

  const LinearSampler sampler(preop);
  out["linear_sampler_gradient_s"] = fastest(repeat, [&] {
    double s = 0, value;
    Eigen::Vector3d g;
    for (const auto& p : world)
      if (sampler.sample(p, &value, &g)) s += value + g.sum();
    check = s;
  });
  out["linear_sampler_gradient_checksum"] = check;

  out["vector_sampling_s"] = fastest(repeat, [&] {
    double s = 0;
    for (const auto& p : voxel)
      if (const auto v = sample_vector_linear_voxel(u, p)) s += v->sum();
    check = s;
  });
  out["vector_sampling_checksum"] = check;

  // Known inside a ball (the mesh's brain), filled everywhere else, as the field stage does.
  std::vector<std::uint8_t> known(target.voxel_count(), 0);
  std::vector<std::uint32_t> targets;
  for (int k = 0; k < target.dims[2]; ++k)
    for (int j = 0; j < target.dims[1]; ++j)
      for (int i = 0; i < target.dims[0]; ++i) {
        const std::size_t v = target.index(i, j, k);
        const bool in = (Eigen::Vector3d(i, j, k) - Eigen::Vector3d::Constant(80)).norm() < 55;
        known[v] = in;
        if (!in) targets.push_back(static_cast<std::uint32_t>(v));
      }
  out["fill_push_pull_s"] = fastest(repeat, [&] {
    std::vector<Eigen::Vector3f> values = u.vectors;
    fill_push_pull(target, known, targets, values);
    double s = 0;
    for (const auto& v : values) s += v.sum();
    check = s;
  });
  out["fill_push_pull_checksum"] = check;
  out["points"] = points;
  out["repeat"] = repeat;
  std::printf("%s\n", out.dump().c_str());
  return 0;
}
