#include "models/carry.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/errors.h"

namespace brainshift {
namespace {

// Uniform grid of buckets; each tet is listed in every bucket its bounding box
// overlaps.
class TetBuckets {
 public:
  explicit TetBuckets(const TetMesh& mesh) : mesh_(mesh) {
    lo_ = Eigen::Vector3d::Constant(std::numeric_limits<double>::max());
    Eigen::Vector3d hi = -lo_;
    double mean_extent = 0;
    for (const auto& t : mesh.tets) {
      Eigen::Vector3d tlo, thi;
      tet_box(t, tlo, thi);
      lo_ = lo_.cwiseMin(tlo);
      hi = hi.cwiseMax(thi);
      mean_extent += (thi - tlo).mean();
    }
    mean_extent /= static_cast<double>(mesh.tets.size());
    // About one tet diameter per bucket, but never more than ~8M buckets.
    const Eigen::Vector3d extent = (hi - lo_).cwiseMax(1e-6);
    cell_mm_ = std::max(mean_extent, std::cbrt(extent.prod() / 8e6));
    for (int a = 0; a < 3; ++a) dims_[a] = std::max(1, static_cast<int>(std::ceil(extent[a] / cell_mm_)));
    fill();
  }

  double cell_mm() const { return cell_mm_; }
  const std::array<int, 3>& dims() const { return dims_; }

  // Unclamped bucket coordinates of a point.
  std::array<int, 3> cell_of(const Eigen::Vector3d& p) const {
    std::array<int, 3> c;
    for (int a = 0; a < 3; ++a) c[a] = static_cast<int>(std::floor((p[a] - lo_[a]) / cell_mm_));
    return c;
  }
  bool valid(int i, int j, int k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < dims_[0] && j < dims_[1] && k < dims_[2];
  }
  template <class F>
  void for_tets_in(int i, int j, int k, F&& f) const {
    const std::size_t b = bucket(i, j, k);
    for (int e = start_[b]; e < start_[b + 1]; ++e) f(entries_[e]);
  }

 private:
  void tet_box(const std::array<int, 4>& t, Eigen::Vector3d& lo, Eigen::Vector3d& hi) const {
    lo = hi = mesh_.nodes_mm[t[0]];
    for (int q = 1; q < 4; ++q) {
      lo = lo.cwiseMin(mesh_.nodes_mm[t[q]]);
      hi = hi.cwiseMax(mesh_.nodes_mm[t[q]]);
    }
  }
  std::size_t bucket(int i, int j, int k) const {
    return static_cast<std::size_t>(i) +
           static_cast<std::size_t>(dims_[0]) * (static_cast<std::size_t>(j) + static_cast<std::size_t>(dims_[1]) * k);
  }
  template <class F>
  void for_buckets_of_tet(std::size_t t, F&& f) const {
    Eigen::Vector3d lo, hi;
    tet_box(mesh_.tets[t], lo, hi);
    auto a = cell_of(lo), b = cell_of(hi);
    for (int d = 0; d < 3; ++d) {
      a[d] = std::clamp(a[d], 0, dims_[d] - 1);
      b[d] = std::clamp(b[d], 0, dims_[d] - 1);
    }
    for (int k = a[2]; k <= b[2]; ++k)
      for (int j = a[1]; j <= b[1]; ++j)
        for (int i = a[0]; i <= b[0]; ++i) f(bucket(i, j, k));
  }
  void fill() {
    start_.assign(static_cast<std::size_t>(dims_[0]) * dims_[1] * dims_[2] + 1, 0);
    for (std::size_t t = 0; t < mesh_.tets.size(); ++t) for_buckets_of_tet(t, [&](std::size_t b) { ++start_[b + 1]; });
    for (std::size_t b = 0; b + 1 < start_.size(); ++b) start_[b + 1] += start_[b];
    entries_.resize(start_.back());
    std::vector<int> cursor(start_.begin(), start_.end() - 1);
    for (std::size_t t = 0; t < mesh_.tets.size(); ++t)
      for_buckets_of_tet(t, [&](std::size_t b) { entries_[cursor[b]++] = static_cast<int>(t); });
  }

  const TetMesh& mesh_;
  Eigen::Vector3d lo_;
  double cell_mm_ = 1;
  std::array<int, 3> dims_{1, 1, 1};
  std::vector<int> start_, entries_;
};

Eigen::Vector4d barycentrics(const TetMesh& m, int t, const Eigen::Vector3d& p) {
  const auto& n = m.tets[t];
  Eigen::Matrix3d e;
  e << m.nodes_mm[n[1]] - m.nodes_mm[n[0]], m.nodes_mm[n[2]] - m.nodes_mm[n[0]], m.nodes_mm[n[3]] - m.nodes_mm[n[0]];
  const Eigen::Vector3d l = e.partialPivLu().solve(p - m.nodes_mm[n[0]]);
  return Eigen::Vector4d(1.0 - l.sum(), l[0], l[1], l[2]);
}

// Closest point to p on triangle abc (Ericson, Real-Time Collision Detection 5.1.5).
Eigen::Vector3d closest_on_triangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                    const Eigen::Vector3d& c) {
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + d1 / (d1 - d3) * ab;
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + d2 / (d2 - d6) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b);
  const double denom = 1.0 / (va + vb + vc);
  return a + ab * (vb * denom) + ac * (vc * denom);
}

Eigen::Vector3d closest_on_tet(const TetMesh& m, int t, const Eigen::Vector3d& p) {
  if (barycentrics(m, t, p).minCoeff() >= 0) return p;
  static constexpr int faces[4][3] = {{1, 2, 3}, {0, 2, 3}, {0, 1, 3}, {0, 1, 2}};
  const auto& n = m.tets[t];
  Eigen::Vector3d best = m.nodes_mm[n[0]];
  double best_d2 = std::numeric_limits<double>::max();
  for (const auto& f : faces) {
    const Eigen::Vector3d q = closest_on_triangle(p, m.nodes_mm[n[f[0]]], m.nodes_mm[n[f[1]]], m.nodes_mm[n[f[2]]]);
    if ((q - p).squaredNorm() < best_d2) {
      best_d2 = (q - p).squaredNorm();
      best = q;
    }
  }
  return best;
}

struct Hit {
  int tet = -1;
  Eigen::Vector4d weights = Eigen::Vector4d::Zero();
  double distance_mm = 0;
};

// Containing tet (the most interior one when p lies on shared faces).
Hit find_containing(const TetMesh& m, const TetBuckets& buckets, const Eigen::Vector3d& p) {
  Hit hit;
  const auto c = buckets.cell_of(p);
  if (!buckets.valid(c[0], c[1], c[2])) return hit;
  double best_min = -1e-9;
  buckets.for_tets_in(c[0], c[1], c[2], [&](int t) {
    const Eigen::Vector4d w = barycentrics(m, t, p);
    if (w.minCoeff() >= best_min) {
      best_min = w.minCoeff();
      hit.tet = t;
      hit.weights = w;
    }
  });
  return hit;
}

// Closest mesh point by searching shells of buckets around p until no closer
// tet can exist.
Hit find_closest(const TetMesh& m, const TetBuckets& buckets, const Eigen::Vector3d& p, std::vector<int>& stamp,
                 int query_id) {
  Hit hit;
  hit.distance_mm = std::numeric_limits<double>::max();
  const auto c = buckets.cell_of(p);
  const auto& d = buckets.dims();
  int max_ring = 0;
  for (int a = 0; a < 3; ++a) max_ring = std::max({max_ring, std::abs(c[a]), std::abs(c[a] - d[a] + 1)});
  Eigen::Vector3d best_point = p;
  for (int r = 0; r <= max_ring; ++r) {
    for (int k = std::max(0, c[2] - r); k <= std::min(d[2] - 1, c[2] + r); ++k)
      for (int j = std::max(0, c[1] - r); j <= std::min(d[1] - 1, c[1] + r); ++j) {
        const bool face = std::abs(k - c[2]) == r || std::abs(j - c[1]) == r;
        for (int i = std::max(0, c[0] - r); i <= std::min(d[0] - 1, c[0] + r); ++i) {
          if (!face && std::abs(i - c[0]) != r) continue;
          buckets.for_tets_in(i, j, k, [&](int t) {
            if (stamp[t] == query_id) return;
            stamp[t] = query_id;
            const Eigen::Vector3d q = closest_on_tet(m, t, p);
            const double dist = (q - p).norm();
            if (dist < hit.distance_mm) {
              hit.distance_mm = dist;
              hit.tet = t;
              best_point = q;
            }
          });
        }
      }
    // Buckets of the next shell are at least r cells away from p's bucket.
    if (hit.tet >= 0 && hit.distance_mm <= r * buckets.cell_mm()) break;
  }
  Eigen::Vector4d w = barycentrics(m, hit.tet, best_point).cwiseMax(0.0);
  hit.weights = w / w.sum();
  return hit;
}

}  // namespace

ModelBinding bind_to_mesh(const TriSurface& preop_model, const TetMesh& preop_mesh) {
  if (preop_mesh.tets.empty()) throw InputError("bind_to_mesh: the mesh has no tetrahedra");
  for (const auto& v : preop_model.vertices_mm)
    if (!v.allFinite()) throw InputError("bind_to_mesh: the model has a non-finite vertex");
  const TetBuckets buckets(preop_mesh);
  ModelBinding b;
  b.mesh_node_count = preop_mesh.node_count();
  b.nodes.resize(preop_model.vertices_mm.size());
  b.weights.resize(preop_model.vertices_mm.size());
  std::vector<int> stamp(preop_mesh.tets.size(), -1);
  for (std::size_t v = 0; v < preop_model.vertices_mm.size(); ++v) {
    const Eigen::Vector3d& p = preop_model.vertices_mm[v];
    Hit hit = find_containing(preop_mesh, buckets, p);
    if (hit.tet < 0) {
      hit = find_closest(preop_mesh, buckets, p, stamp, static_cast<int>(v));
      ++b.vertices_outside;
      b.max_distance_outside_mm = std::max(b.max_distance_outside_mm, hit.distance_mm);
    } else {
      hit.weights = hit.weights.cwiseMax(0.0);
      hit.weights /= hit.weights.sum();
    }
    b.nodes[v] = preop_mesh.tets[hit.tet];
    for (int q = 0; q < 4; ++q) b.weights[v][q] = hit.weights[q];
  }
  return b;
}

TriSurface carry(const TriSurface& preop_model, const ModelBinding& binding, const MeshDeformation& deformation) {
  if (binding.nodes.size() != preop_model.vertices_mm.size())
    throw InputError("carry: the binding was made for a model with a different number of vertices");
  if (deformation.nonrigid_mm.size() != binding.mesh_node_count)
    throw InputError("carry: the deformation has " + std::to_string(deformation.nonrigid_mm.size()) +
                     " nodal residuals but the model was bound to a mesh of " +
                     std::to_string(binding.mesh_node_count) + " nodes");
  TriSurface out;
  out.triangles = preop_model.triangles;
  out.vertices_mm.resize(preop_model.vertices_mm.size());
  const Eigen::Matrix3d linear = deformation.intraop_from_preop.topLeftCorner<3, 3>();
  const Eigen::Vector3d shift = deformation.intraop_from_preop.topRightCorner<3, 1>();
  const auto& w = deformation.nonrigid_mm;
  for (std::size_t v = 0; v < out.vertices_mm.size(); ++v) {
    const auto& n = binding.nodes[v];
    const auto& l = binding.weights[v];
    out.vertices_mm[v] = linear * preop_model.vertices_mm[v] + shift + l[0] * w[n[0]] + l[1] * w[n[1]] +
                         l[2] * w[n[2]] + l[3] * w[n[3]];
  }
  return out;
}

}  // namespace brainshift
