#include "models/carry.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <utility>

#include "core/errors.h"

namespace brainshift {
namespace {

using Box = std::pair<Eigen::Vector3d, Eigen::Vector3d>;

// Uniform grid of buckets over items with bounding boxes; each item is listed
// in every bucket its box overlaps.
class BucketGrid {
 public:
  // cell_mm: wanted bucket size; capped so that there are at most ~8M buckets.
  BucketGrid(const std::vector<Box>& boxes, double cell_mm) {
    lo_ = Eigen::Vector3d::Constant(std::numeric_limits<double>::max());
    Eigen::Vector3d hi = -lo_;
    for (const auto& b : boxes) {
      lo_ = lo_.cwiseMin(b.first);
      hi = hi.cwiseMax(b.second);
    }
    const Eigen::Vector3d extent = (hi - lo_).cwiseMax(1e-6);
    cell_mm_ = std::max({cell_mm, std::cbrt(extent.prod() / 8e6), 1e-6});
    for (int a = 0; a < 3; ++a) dims_[a] = std::max(1, static_cast<int>(std::ceil(extent[a] / cell_mm_)));
    start_.assign(static_cast<std::size_t>(dims_[0]) * dims_[1] * dims_[2] + 1, 0);
    for (const auto& b : boxes) for_buckets(b, [&](std::size_t c) { ++start_[c + 1]; });
    for (std::size_t c = 0; c + 1 < start_.size(); ++c) start_[c + 1] += start_[c];
    entries_.resize(start_.back());
    std::vector<int> cursor(start_.begin(), start_.end() - 1);
    for (std::size_t i = 0; i < boxes.size(); ++i)
      for_buckets(boxes[i], [&](std::size_t c) { entries_[cursor[c]++] = static_cast<int>(i); });
  }

  double cell_mm() const { return cell_mm_; }
  const std::array<int, 3>& dims() const { return dims_; }
  // Unclamped bucket coordinates of a point.
  std::array<int, 3> cell_of(const Eigen::Vector3d& p) const {
    std::array<int, 3> c;
    for (int a = 0; a < 3; ++a) c[a] = static_cast<int>(std::floor((p[a] - lo_[a]) / cell_mm_));
    return c;
  }
  bool valid(const std::array<int, 3>& c) const {
    return c[0] >= 0 && c[1] >= 0 && c[2] >= 0 && c[0] < dims_[0] && c[1] < dims_[1] && c[2] < dims_[2];
  }
  template <class F>
  void for_items_in(int i, int j, int k, F&& f) const {
    const std::size_t b = bucket(i, j, k);
    for (int e = start_[b]; e < start_[b + 1]; ++e) f(entries_[e]);
  }
  // Visits the items of the buckets at Chebyshev distance r from cell c.
  template <class F>
  void for_items_in_shell(const std::array<int, 3>& c, int r, F&& f) const {
    for (int k = std::max(0, c[2] - r); k <= std::min(dims_[2] - 1, c[2] + r); ++k)
      for (int j = std::max(0, c[1] - r); j <= std::min(dims_[1] - 1, c[1] + r); ++j) {
        const bool face = std::abs(k - c[2]) == r || std::abs(j - c[1]) == r;
        for (int i = std::max(0, c[0] - r); i <= std::min(dims_[0] - 1, c[0] + r); ++i)
          if (face || std::abs(i - c[0]) == r) for_items_in(i, j, k, f);
      }
  }
  // Largest shell radius that can still contain buckets.
  int max_ring(const std::array<int, 3>& c) const {
    int r = 0;
    for (int a = 0; a < 3; ++a) r = std::max({r, std::abs(c[a]), std::abs(c[a] - dims_[a] + 1)});
    return r;
  }

 private:
  std::size_t bucket(int i, int j, int k) const {
    return static_cast<std::size_t>(i) +
           static_cast<std::size_t>(dims_[0]) * (static_cast<std::size_t>(j) + static_cast<std::size_t>(dims_[1]) * k);
  }
  template <class F>
  void for_buckets(const Box& b, F&& f) const {
    auto a = cell_of(b.first), z = cell_of(b.second);
    for (int d = 0; d < 3; ++d) {
      a[d] = std::clamp(a[d], 0, dims_[d] - 1);
      z[d] = std::clamp(z[d], 0, dims_[d] - 1);
    }
    for (int k = a[2]; k <= z[2]; ++k)
      for (int j = a[1]; j <= z[1]; ++j)
        for (int i = a[0]; i <= z[0]; ++i) f(bucket(i, j, k));
  }

  Eigen::Vector3d lo_;
  double cell_mm_ = 1;
  std::array<int, 3> dims_{1, 1, 1};
  std::vector<int> start_, entries_;
};

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

// The mesh prepared for point location: per-tet inverse edge matrices, tet
// buckets, and the boundary triangles (faces used by one tet: the outer
// surface and cavity walls, derived from the tets so that any TetMesh works)
// with their own buckets for closest-point queries from outside.
class MeshLocator {
 public:
  explicit MeshLocator(const TetMesh& m) : m_(m) {
    const std::size_t nt = m.tets.size();
    inverse_.resize(nt);
    std::vector<Box> boxes(nt);
    double mean_extent = 0;
    for (std::size_t t = 0; t < nt; ++t) {
      const auto& n = m.tets[t];
      Eigen::Matrix3d e;
      e << m.nodes_mm[n[1]] - m.nodes_mm[n[0]], m.nodes_mm[n[2]] - m.nodes_mm[n[0]], m.nodes_mm[n[3]] - m.nodes_mm[n[0]];
      inverse_[t] = e.inverse();
      boxes[t] = box_of({n[0], n[1], n[2], n[3]});
      mean_extent += (boxes[t].second - boxes[t].first).mean();
    }
    tets_ = std::make_unique<BucketGrid>(boxes, mean_extent / static_cast<double>(nt));
    find_boundary();
  }

  Eigen::Vector4d barycentrics(int t, const Eigen::Vector3d& p) const {
    const Eigen::Vector3d l = inverse_[t] * (p - m_.nodes_mm[m_.tets[t][0]]);
    return Eigen::Vector4d(1.0 - l.sum(), l[0], l[1], l[2]);
  }

  // Containing tet (the most interior one when p lies on shared faces), or -1.
  int containing(const Eigen::Vector3d& p, Eigen::Vector4d& weights) const {
    const auto c = tets_->cell_of(p);
    if (!tets_->valid(c)) return -1;
    int best = -1;
    double best_min = -1e-9;
    tets_->for_items_in(c[0], c[1], c[2], [&](int t) {
      const Eigen::Vector4d w = barycentrics(t, p);
      if (w.minCoeff() >= best_min) {
        best_min = w.minCoeff();
        best = t;
        weights = w;
      }
    });
    return best;
  }

  // Closest point on the mesh boundary: its tet, barycentrics and distance.
  int closest(const Eigen::Vector3d& p, Eigen::Vector4d& weights, double& distance_mm) const {
    const auto c = faces_->cell_of(p);
    distance_mm = std::numeric_limits<double>::max();
    int best_face = -1;
    Eigen::Vector3d best_point = p;
    for (int r = 0, last = faces_->max_ring(c); r <= last; ++r) {
      faces_->for_items_in_shell(c, r, [&](int f) {
        const auto& tri = faces_tri_[f];
        const Eigen::Vector3d q = closest_on_triangle(p, m_.nodes_mm[tri[0]], m_.nodes_mm[tri[1]], m_.nodes_mm[tri[2]]);
        const double d = (q - p).norm();
        if (d < distance_mm) {
          distance_mm = d;
          best_face = f;
          best_point = q;
        }
      });
      // Buckets of the next shell are at least r cells away.
      if (best_face >= 0 && distance_mm <= r * faces_->cell_mm()) break;
    }
    const int t = faces_owner_[best_face];
    weights = barycentrics(t, best_point);
    return t;
  }

 private:
  Box box_of(std::initializer_list<int> nodes) const {
    Box b{m_.nodes_mm[*nodes.begin()], m_.nodes_mm[*nodes.begin()]};
    for (int n : nodes) {
      b.first = b.first.cwiseMin(m_.nodes_mm[n]);
      b.second = b.second.cwiseMax(m_.nodes_mm[n]);
    }
    return b;
  }

  void find_boundary() {
    struct Face {
      std::array<int, 3> key;
      int tet, opposite;
    };
    std::vector<Face> faces;
    faces.reserve(4 * m_.tets.size());
    for (std::size_t t = 0; t < m_.tets.size(); ++t)
      for (int o = 0; o < 4; ++o) {
        std::array<int, 3> key;
        for (int q = 0, n = 0; q < 4; ++q)
          if (q != o) key[n++] = m_.tets[t][q];
        std::sort(key.begin(), key.end());
        faces.push_back({key, static_cast<int>(t), o});
      }
    std::sort(faces.begin(), faces.end(), [](const Face& a, const Face& b) { return a.key < b.key; });
    std::vector<Box> boxes;
    double mean_extent = 0;
    for (std::size_t f = 0; f < faces.size();) {
      std::size_t g = f + 1;
      while (g < faces.size() && faces[g].key == faces[f].key) ++g;
      if (g - f == 1) {
        faces_tri_.push_back(faces[f].key);
        faces_owner_.push_back(faces[f].tet);
        boxes.push_back(box_of({faces[f].key[0], faces[f].key[1], faces[f].key[2]}));
        mean_extent += (boxes.back().second - boxes.back().first).mean();
      }
      f = g;
    }
    faces_ = std::make_unique<BucketGrid>(boxes, 2.0 * mean_extent / std::max<std::size_t>(1, boxes.size()));
  }

  const TetMesh& m_;
  std::vector<Eigen::Matrix3d> inverse_;
  std::unique_ptr<BucketGrid> tets_, faces_;
  std::vector<std::array<int, 3>> faces_tri_;
  std::vector<int> faces_owner_;
};

}  // namespace

ModelBinding bind_to_mesh(const TriSurface& preop_model, const TetMesh& preop_mesh) {
  if (preop_mesh.tets.empty()) throw InputError("bind_to_mesh: the mesh has no tetrahedra");
  for (const auto& v : preop_model.vertices_mm)
    if (!v.allFinite()) throw InputError("bind_to_mesh: the model has a non-finite vertex");
  const MeshLocator locator(preop_mesh);
  ModelBinding b;
  b.mesh_node_count = preop_mesh.node_count();
  b.nodes.resize(preop_model.vertices_mm.size());
  b.weights.resize(preop_model.vertices_mm.size());
  for (std::size_t v = 0; v < preop_model.vertices_mm.size(); ++v) {
    const Eigen::Vector3d& p = preop_model.vertices_mm[v];
    Eigen::Vector4d w;
    int tet = locator.containing(p, w);
    if (tet < 0) {
      double distance = 0;
      tet = locator.closest(p, w, distance);
      ++b.vertices_outside;
      b.max_distance_outside_mm = std::max(b.max_distance_outside_mm, distance);
    }
    // Clamp rounding noise (and the closest point's zero on its face).
    w = w.cwiseMax(0.0);
    w /= w.sum();
    b.nodes[v] = preop_mesh.tets[tet];
    for (int q = 0; q < 4; ++q) b.weights[v][q] = w[q];
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
