#include "registration/surface_repair.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <unordered_map>

namespace brainshift {
namespace {

// Unmarked vertices bucketed in cubes of `cell` mm.
class VertexGrid {
 public:
  VertexGrid(const std::vector<Eigen::Vector3d>& p, const std::vector<char>& marked, double cell) : cell_(cell) {
    for (std::size_t v = 0; v < p.size(); ++v)
      if (!marked[v]) cells_[key(cell_of(p[v]))].push_back(static_cast<int>(v));
  }
  // Calls fn(vertex) for every bucketed vertex in the cubes that overlap the
  // ball of radius r around x (r <= reach * cell).
  template <class F>
  void around(const Eigen::Vector3d& x, int reach, F&& fn) const {
    const Eigen::Vector3i c = cell_of(x);
    for (int dz = -reach; dz <= reach; ++dz)
      for (int dy = -reach; dy <= reach; ++dy)
        for (int dx = -reach; dx <= reach; ++dx) {
          const auto it = cells_.find(key(c + Eigen::Vector3i(dx, dy, dz)));
          if (it == cells_.end()) continue;
          for (int v : it->second) fn(v);
        }
  }

 private:
  Eigen::Vector3i cell_of(const Eigen::Vector3d& x) const {
    return (x / cell_).array().floor().cast<int>();
  }
  static std::int64_t key(const Eigen::Vector3i& c) {
    return (static_cast<std::int64_t>(c.x() + (1 << 20)) << 42) ^ (static_cast<std::int64_t>(c.y() + (1 << 20)) << 21) ^
           static_cast<std::int64_t>(c.z() + (1 << 20));
  }
  double cell_;
  std::unordered_map<std::int64_t, std::vector<int>> cells_;
};

}  // namespace

std::vector<std::vector<int>> surface_vertex_neighbours(const TriSurface& s) {
  std::vector<std::vector<int>> nb(s.vertices_mm.size());
  for (const auto& t : s.triangles)
    for (int c = 0; c < 3; ++c) {
      nb[t[c]].push_back(t[(c + 1) % 3]);
      nb[t[c]].push_back(t[(c + 2) % 3]);
    }
  for (auto& list : nb) {
    std::sort(list.begin(), list.end());
    list.erase(std::unique(list.begin(), list.end()), list.end());
  }
  return nb;
}

void grow_marked(std::vector<char>& marked, const std::vector<std::vector<int>>& nb, int rings) {
  for (int r = 0; r < rings; ++r) {
    const std::vector<char> before = marked;
    for (std::size_t v = 0; v < before.size(); ++v)
      if (before[v])
        for (int w : nb[v]) marked[w] = 1;
  }
}

std::size_t fill_from_reliable_neighbours(const std::vector<Eigen::Vector3d>& p, const std::vector<char>& marked,
                                          std::vector<Eigen::Vector3d>& u, double sigma_mm, double max_search_mm) {
  const double cell = 3 * sigma_mm;
  const VertexGrid grid(p, marked, cell);
  std::vector<Eigen::Vector3d> filled = u;
  std::size_t unreached = 0;
  for (std::size_t v = 0; v < p.size(); ++v) {
    if (!marked[v]) continue;
    bool found = false;
    // Widen the kernel until reliable vertices are in reach: a defect patch
    // wider than 3 sigma takes a wider mean toward its middle.
    for (double sigma = sigma_mm; !found && 3 * sigma <= max_search_mm + 1e-9; sigma *= 2) {
      const double radius = 3 * sigma;
      const int reach = static_cast<int>(std::ceil(radius / cell));
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      double weight = 0;
      grid.around(p[v], reach, [&](int w) {
        const double d2 = (p[w] - p[v]).squaredNorm();
        if (d2 > radius * radius) return;
        const double k = std::exp(-0.5 * d2 / (sigma * sigma));
        sum += k * u[w];
        weight += k;
      });
      if (weight > 1e-12) {
        filled[v] = sum / weight;
        found = true;
      }
    }
    if (!found) {
      filled[v] = Eigen::Vector3d::Zero();  // the affine alone
      ++unreached;
    }
  }
  u = std::move(filled);
  return unreached;
}

std::vector<int> flipped_triangles(const TriSurface& start, const std::vector<Eigen::Vector3d>& x) {
  std::vector<int> out;
  const auto& p = start.vertices_mm;
  for (std::size_t t = 0; t < start.triangles.size(); ++t) {
    const auto& tri = start.triangles[t];
    const Eigen::Vector3d n0 = (p[tri[1]] - p[tri[0]]).cross(p[tri[2]] - p[tri[0]]);
    const Eigen::Vector3d n1 = (x[tri[1]] - x[tri[0]]).cross(x[tri[2]] - x[tri[0]]);
    if (!(n0.dot(n1) > 0)) out.push_back(static_cast<int>(t));
  }
  return out;
}

FoldLimiter::FoldLimiter(const TriSurface& start, const FoldGuard& guard)
    : start_(start), guard_(guard), cos_max_(std::cos(guard.max_normal_turn_deg * M_PI / 180.0)),
      n0_(start.triangles.size()), triangles_of_(start.vertices_mm.size()) {
  const auto& p = start.vertices_mm;
  for (std::size_t t = 0; t < n0_.size(); ++t) {
    const auto& tri = start.triangles[t];
    n0_[t] = (p[tri[1]] - p[tri[0]]).cross(p[tri[2]] - p[tri[0]]);
    for (int v : tri) triangles_of_[v].push_back(static_cast<int>(t));
  }
}

bool FoldLimiter::keeps_guard(int t, const std::vector<Eigen::Vector3d>& x) const {
  const double a0 = n0_[t].norm();
  if (!(a0 > 1e-12)) return true;
  const auto& tri = start_.triangles[static_cast<std::size_t>(t)];
  const Eigen::Vector3d n1 = (x[tri[1]] - x[tri[0]]).cross(x[tri[2]] - x[tri[0]]);
  const double a1 = n1.norm();
  return n0_[t].dot(n1) >= cos_max_ * a0 * a1 && a1 >= guard_.min_area_ratio * a0;
}

std::size_t FoldLimiter::limit(const std::vector<Eigen::Vector3d>& from, std::vector<Eigen::Vector3d>& to) const {
  const auto& p = start_.vertices_mm;
  const std::size_t n = p.size();
  std::vector<double> lambda(n, 1.0);
  std::vector<Eigen::Vector3d> x(n);
  for (std::size_t v = 0; v < n; ++v) x[v] = p[v] + to[v];
  std::vector<int> check(start_.triangles.size()), bad;
  for (std::size_t t = 0; t < check.size(); ++t) check[t] = static_cast<int>(t);
  std::vector<char> marked(n, 0), queued(start_.triangles.size(), 0);
  std::vector<int> changed;
  constexpr int kHalvings = 4;
  // Each pass after the halvings zeroes the step of at least one more vertex
  // (a triangle whose three vertices keep their `from` position keeps the
  // guard), so the passes end on any surface; the cap only bounds the loop
  // when `from` itself breaks the guard. Only the triangles around the
  // vertices a pass changed are checked again.
  for (int pass = 0; pass < 64 && !check.empty(); ++pass) {
    changed.clear();
    for (int t : check) {
      if (keeps_guard(t, x)) continue;
      for (int v : start_.triangles[static_cast<std::size_t>(t)])
        if (!marked[v] && lambda[v] > 0) marked[v] = 1, changed.push_back(v);
    }
    check.clear();
    for (int v : changed) {
      marked[v] = 0;
      lambda[v] = pass < kHalvings ? 0.5 * lambda[v] : 0.0;
      x[v] = p[v] + from[v] + lambda[v] * (to[v] - from[v]);
      for (int t : triangles_of_[v])
        if (!queued[t]) queued[t] = 1, check.push_back(t);
    }
    for (int t : check) queued[t] = 0;
  }
  std::size_t held = 0;
  for (std::size_t v = 0; v < n; ++v) {
    if (lambda[v] < 1.0) ++held;
    to[v] = from[v] + lambda[v] * (to[v] - from[v]);
  }
  return held;
}

std::size_t limit_folding(const TriSurface& start, const std::vector<Eigen::Vector3d>& from,
                          std::vector<Eigen::Vector3d>& to, const FoldGuard& guard) {
  return FoldLimiter(start, guard).limit(from, to);
}

std::vector<double> vertex_areas_mm2(const TriSurface& s) {
  std::vector<double> a(s.vertices_mm.size(), 0.0);
  for (const auto& t : s.triangles) {
    const double area = 0.5 * (s.vertices_mm[t[1]] - s.vertices_mm[t[0]]).cross(s.vertices_mm[t[2]] - s.vertices_mm[t[0]]).norm();
    for (int v : t) a[v] += area / 3.0;
  }
  return a;
}

}  // namespace brainshift
