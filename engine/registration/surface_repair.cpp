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

std::vector<double> vertex_areas_mm2(const TriSurface& s) {
  std::vector<double> a(s.vertices_mm.size(), 0.0);
  for (const auto& t : s.triangles) {
    const double area = 0.5 * (s.vertices_mm[t[1]] - s.vertices_mm[t[0]]).cross(s.vertices_mm[t[2]] - s.vertices_mm[t[0]]).norm();
    for (int v : t) a[v] += area / 3.0;
  }
  return a;
}

}  // namespace brainshift
