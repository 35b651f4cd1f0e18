#include "models/surface_models.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <unordered_map>

#include "core/errors.h"

namespace brainshift {
namespace {

// A cropped, padded float copy of the mask, in voxel index space of the source
// grid shifted by `offset` (source index = local index + offset).
struct Field {
  std::array<int, 3> dims{0, 0, 0};
  std::array<int, 3> offset{0, 0, 0};
  std::vector<float> values;
  std::size_t index(int i, int j, int k) const {
    return static_cast<std::size_t>(i) +
           static_cast<std::size_t>(dims[0]) *
               (static_cast<std::size_t>(j) + static_cast<std::size_t>(dims[1]) * k);
  }
};

void validate(const LabelImage& labels, const ModelParameters& p) {
  if (labels.grid.voxel_count() == 0 || labels.voxels.size() != labels.grid.voxel_count())
    throw InputError("surface_model: label image is empty or its voxel count does not match its grid");
  if (!(p.presmooth_sigma_mm >= 0) || p.taubin_iterations < 0 || !(p.taubin_lambda > 0) ||
      !(p.taubin_mu < -p.taubin_lambda) || !(p.min_edge_fraction >= 0 && p.min_edge_fraction < 1))
    throw InputError(
        "surface_model: parameters need presmooth_sigma_mm >= 0, taubin_iterations >= 0, "
        "taubin_lambda > 0, taubin_mu < -taubin_lambda (otherwise smoothing shrinks) and "
        "min_edge_fraction in [0, 1)");
}

// Sigma in voxels per axis; 0 where blurring would be a no-op.
std::array<double, 3> sigma_voxels(const Grid3& grid, double sigma_mm) {
  const Eigen::Vector3d spacing = grid.spacing_mm();
  std::array<double, 3> s{};
  for (int a = 0; a < 3; ++a) {
    s[a] = sigma_mm / spacing[a];
    if (s[a] < 0.25) s[a] = 0;
  }
  return s;
}

// Crops to the structure's bounding box plus a margin wide enough for the blur
// and for closing the surface where the structure touches the image border
// (outside the image counts as background).
bool make_field(const LabelImage& labels, const std::vector<std::uint16_t>& in_structure,
                const std::array<double, 3>& sigma_vox, Field& f) {
  std::array<bool, 65536> wanted{};
  for (auto l : in_structure) wanted[l] = true;
  const auto& d = labels.grid.dims;
  std::array<int, 3> lo{d[0], d[1], d[2]}, hi{-1, -1, -1};
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i)
        if (wanted[labels.at(i, j, k)]) {
          lo = {std::min(lo[0], i), std::min(lo[1], j), std::min(lo[2], k)};
          hi = {std::max(hi[0], i), std::max(hi[1], j), std::max(hi[2], k)};
        }
  if (hi[0] < 0) return false;
  for (int a = 0; a < 3; ++a) {
    const int margin = 2 + static_cast<int>(std::ceil(3.0 * sigma_vox[a]));
    f.offset[a] = lo[a] - margin;
    f.dims[a] = hi[a] - lo[a] + 1 + 2 * margin;
  }
  f.values.assign(static_cast<std::size_t>(f.dims[0]) * f.dims[1] * f.dims[2], 0.f);
  for (int k = lo[2]; k <= hi[2]; ++k)
    for (int j = lo[1]; j <= hi[1]; ++j)
      for (int i = lo[0]; i <= hi[0]; ++i)
        if (wanted[labels.at(i, j, k)])
          f.values[f.index(i - f.offset[0], j - f.offset[1], k - f.offset[2])] = 1.f;
  return true;
}

void blur_axis(Field& f, int axis, double sigma) {
  if (sigma <= 0) return;
  const int radius = static_cast<int>(std::ceil(3.0 * sigma));
  std::vector<float> kernel(2 * radius + 1);
  double sum = 0;
  for (int r = -radius; r <= radius; ++r) sum += kernel[r + radius] = static_cast<float>(std::exp(-0.5 * r * r / (sigma * sigma)));
  for (auto& w : kernel) w = static_cast<float>(w / sum);

  const int n = f.dims[axis];
  const std::size_t stride = axis == 0 ? 1 : axis == 1 ? f.dims[0] : static_cast<std::size_t>(f.dims[0]) * f.dims[1];
  const int o1 = (axis + 1) % 3, o2 = (axis + 2) % 3;
  std::vector<float> line(n), out(n);
  for (int b = 0; b < f.dims[o2]; ++b)
    for (int a = 0; a < f.dims[o1]; ++a) {
      std::array<int, 3> start{0, 0, 0};
      start[o1] = a;
      start[o2] = b;
      const std::size_t base = f.index(start[0], start[1], start[2]);
      for (int t = 0; t < n; ++t) line[t] = f.values[base + t * stride];
      for (int t = 0; t < n; ++t) {
        float acc = 0;
        for (int r = -radius; r <= radius; ++r) {
          const int s = t + r;
          if (s >= 0 && s < n) acc += kernel[r + radius] * line[s];  // zero outside
        }
        out[t] = acc;
      }
      for (int t = 0; t < n; ++t) f.values[base + t * stride] = out[t];
    }
}

// The six Kuhn tets of a unit cube, corners numbered by bits (x=1, y=2, z=4),
// each listed positively oriented in index space. All cubes split their faces
// along the diagonal from the face's lowest to its highest corner, so the
// tetrahedralisation is conforming across cubes.
std::array<std::array<int, 4>, 6> kuhn_tets() {
  std::array<std::array<int, 4>, 6> tets{};
  std::array<int, 3> perm{0, 1, 2};
  int t = 0;
  do {
    const int c1 = 1 << perm[0], c2 = c1 | (1 << perm[1]);
    std::array<int, 4> tet{0, c1, c2, 7};
    auto corner = [](int c) { return Eigen::Vector3d(c & 1, (c >> 1) & 1, (c >> 2) & 1); };
    const Eigen::Vector3d a = corner(tet[1]) - corner(tet[0]), b = corner(tet[2]) - corner(tet[0]),
                          c = corner(tet[3]) - corner(tet[0]);
    if (a.dot(b.cross(c)) < 0) std::swap(tet[2], tet[3]);
    tets[t++] = tet;
  } while (std::next_permutation(perm.begin(), perm.end()));
  return tets;
}

class TetContourer {
 public:
  explicit TetContourer(const Field& f) : f_(f) { edge_vertex_.reserve(1 << 16); }

  void run() {
    const auto tets = kuhn_tets();
    const auto& d = f_.dims;
    for (int k = 0; k + 1 < d[2]; ++k)
      for (int j = 0; j + 1 < d[1]; ++j)
        for (int i = 0; i + 1 < d[0]; ++i) {
          std::array<std::size_t, 8> idx;
          std::array<float, 8> val;
          int inside = 0;
          for (int c = 0; c < 8; ++c) {
            idx[c] = f_.index(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
            val[c] = f_.values[idx[c]];
            inside += val[c] > kIso;
          }
          if (inside == 0 || inside == 8) continue;
          for (const auto& t : tets) contour_tet(t, idx, val);
        }
  }

  TriSurface take(const Grid3& grid) {
    TriSurface s;
    const Eigen::Matrix4d& w = grid.world_from_voxel;
    s.vertices_mm.reserve(positions_.size());
    for (const auto& p : positions_) {
      const Eigen::Vector3d v(p[0] + f_.offset[0], p[1] + f_.offset[1], p[2] + f_.offset[2]);
      s.vertices_mm.push_back((w * v.homogeneous()).head<3>());
    }
    // Orientation was decided in index space; a handedness-flipping affine
    // mirrors it.
    const bool flips = w.topLeftCorner<3, 3>().determinant() < 0;
    for (auto t : triangles_) {
      if (flips) std::swap(t[1], t[2]);
      s.triangles.push_back(t);
    }
    return s;
  }

 private:
  static constexpr float kIso = 0.5f;

  Eigen::Vector3d grid_point(std::size_t linear) const {
    const std::size_t nx = f_.dims[0], nxy = nx * f_.dims[1];
    return Eigen::Vector3d(static_cast<double>(linear % nx), static_cast<double>((linear % nxy) / nx),
                           static_cast<double>(linear / nxy));
  }

  // Vertex on the grid edge between two corners, shared by every tet using it.
  int edge_vertex(std::size_t a, float va, std::size_t b, float vb) {
    if (a > b) {
      std::swap(a, b);
      std::swap(va, vb);
    }
    const std::uint64_t key = static_cast<std::uint64_t>(a) * (static_cast<std::uint64_t>(f_.values.size()) + 1) + (b - a);
    auto [it, fresh] = edge_vertex_.try_emplace(key, static_cast<int>(positions_.size()));
    if (fresh) {
      // Clamped so no two edge vertices coincide at a grid point (that would
      // give zero-area triangles).
      const double t = std::clamp(static_cast<double>(kIso - va) / (vb - va), 1e-3, 1.0 - 1e-3);
      positions_.push_back(grid_point(a) + t * (grid_point(b) - grid_point(a)));
    }
    return it->second;
  }

  void contour_tet(const std::array<int, 4>& t, const std::array<std::size_t, 8>& idx,
                   const std::array<float, 8>& val) {
    std::array<int, 4> in, out;
    int n_in = 0, n_out = 0;
    for (int c : t) (val[c] > kIso ? in[n_in++] : out[n_out++]) = c;
    if (n_in == 0 || n_in == 4) return;
    auto ev = [&](int p, int q) { return edge_vertex(idx[p], val[p], idx[q], val[q]); };
    // Each case reorders the tet by an even permutation (keeping it positive)
    // and emits the triangles whose normals point from inside to outside.
    const std::array<int, 4> v = reorder(t, in, n_in);
    if (n_in == 1) {
      triangles_.push_back({ev(v[0], v[1]), ev(v[0], v[2]), ev(v[0], v[3])});
    } else if (n_in == 3) {
      triangles_.push_back({ev(v[0], v[1]), ev(v[0], v[3]), ev(v[0], v[2])});
    } else {
      // v = (in1, in2, out1, out2); quad cycle a-b-c-d.
      const int a = ev(v[0], v[2]), b = ev(v[0], v[3]), c = ev(v[1], v[3]), d = ev(v[1], v[2]);
      if ((positions_[a] - positions_[c]).squaredNorm() <= (positions_[b] - positions_[d]).squaredNorm()) {
        triangles_.push_back({a, b, c});
        triangles_.push_back({a, c, d});
      } else {
        triangles_.push_back({a, b, d});
        triangles_.push_back({b, c, d});
      }
    }
  }

  // Returns the tet's corners as an even permutation of t such that: for one
  // inside corner it comes first; for one outside corner it comes first; for
  // two, the two inside corners come first.
  static std::array<int, 4> reorder(const std::array<int, 4>& t, const std::array<int, 4>& in, int n_in) {
    std::array<int, 4> pos{};  // position in t of the wanted order
    auto where = [&](int c) { return static_cast<int>(std::find(t.begin(), t.end(), c) - t.begin()); };
    std::array<int, 4> order{};
    int n = 0;
    if (n_in == 1 || n_in == 3) {
      int lone = -1;
      if (n_in == 1) {
        lone = in[0];
      } else {
        for (int c : t)
          if (std::find(in.begin(), in.begin() + 3, c) == in.begin() + 3) lone = c;
      }
      order[n++] = lone;
      for (int c : t)
        if (c != lone) order[n++] = c;
    } else {
      order[n++] = in[0];
      order[n++] = in[1];
      for (int c : t)
        if (c != in[0] && c != in[1]) order[n++] = c;
    }
    for (int q = 0; q < 4; ++q) pos[q] = where(order[q]);
    // Parity of the permutation pos; fix an odd one by swapping the last two.
    int inversions = 0;
    for (int a = 0; a < 4; ++a)
      for (int b = a + 1; b < 4; ++b) inversions += pos[a] > pos[b];
    if (inversions % 2) std::swap(order[2], order[3]);
    return order;
  }

  const Field& f_;
  std::unordered_map<std::uint64_t, int> edge_vertex_;
  std::vector<Eigen::Vector3d> positions_;
  std::vector<std::array<int, 3>> triangles_;
};

// Removes the very short edges marching tetrahedra leaves where the surface
// passes close to grid points, by edge collapse to the midpoint. A collapse is
// done only when it keeps a closed 2-manifold (link condition: the edge's end
// points share exactly the two opposite vertices, each of which keeps >= 3
// neighbours) and flips no triangle (normals turn by less than ~80 degrees).
class ShortEdgeCollapser {
 public:
  explicit ShortEdgeCollapser(TriSurface& s) : s_(s), vt_(s.vertices_mm.size()), dead_(s.triangles.size(), 0) {
    for (std::size_t t = 0; t < s.triangles.size(); ++t)
      for (int v : s.triangles[t]) vt_[v].push_back(static_cast<int>(t));
  }

  void run(double min_edge_mm, int passes) {
    const double min2 = min_edge_mm * min_edge_mm;
    for (int pass = 0; pass < passes; ++pass) {
      std::size_t collapsed = 0;
      for (std::size_t t = 0; t < s_.triangles.size(); ++t)
        for (int e = 0; e < 3 && !dead_[t]; ++e) {
          const int a = s_.triangles[t][e], b = s_.triangles[t][(e + 1) % 3];
          if ((s_.vertices_mm[a] - s_.vertices_mm[b]).squaredNorm() < min2 && collapse(a, b)) ++collapsed;
        }
      if (collapsed == 0) break;
    }
    compact();
  }

 private:
  std::vector<int> neighbours(int v) const {
    std::vector<int> n;
    for (int t : vt_[v])
      for (int w : s_.triangles[t])
        if (w != v) n.push_back(w);
    std::sort(n.begin(), n.end());
    n.erase(std::unique(n.begin(), n.end()), n.end());
    return n;
  }

  static Eigen::Vector3d normal(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
    return (b - a).cross(c - a);
  }

  bool collapse(int a, int b) {
    std::vector<int> shared;
    for (int t : vt_[a])
      if (std::find(s_.triangles[t].begin(), s_.triangles[t].end(), b) != s_.triangles[t].end()) shared.push_back(t);
    if (shared.size() != 2) return false;
    std::vector<int> opposite;
    for (int t : shared)
      for (int w : s_.triangles[t])
        if (w != a && w != b) opposite.push_back(w);
    std::sort(opposite.begin(), opposite.end());
    const auto na = neighbours(a), nb = neighbours(b);
    std::vector<int> common;
    std::set_intersection(na.begin(), na.end(), nb.begin(), nb.end(), std::back_inserter(common));
    if (common != opposite || opposite[0] == opposite[1]) return false;
    for (int o : opposite)
      if (neighbours(o).size() <= 3) return false;
    const Eigen::Vector3d mid = 0.5 * (s_.vertices_mm[a] + s_.vertices_mm[b]);
    for (int v : {a, b})
      for (int t : vt_[v]) {
        if (t == shared[0] || t == shared[1]) continue;
        std::array<Eigen::Vector3d, 3> p;
        for (int q = 0; q < 3; ++q) {
          const int w = s_.triangles[t][q];
          p[q] = (w == a || w == b) ? mid : s_.vertices_mm[w];
        }
        const Eigen::Vector3d before = normal(s_.vertices_mm[s_.triangles[t][0]], s_.vertices_mm[s_.triangles[t][1]],
                                              s_.vertices_mm[s_.triangles[t][2]]);
        const Eigen::Vector3d after = normal(p[0], p[1], p[2]);
        if (before.dot(after) <= 0.2 * before.norm() * after.norm()) return false;
      }
    for (int t : shared) {
      dead_[t] = 1;
      for (int w : s_.triangles[t]) std::erase(vt_[w], t);
    }
    for (int t : vt_[b]) {
      for (int& w : s_.triangles[t])
        if (w == b) w = a;
      vt_[a].push_back(t);
    }
    vt_[b].clear();
    s_.vertices_mm[a] = mid;
    return true;
  }

  void compact() {
    std::vector<int> new_index(s_.vertices_mm.size(), -1);
    std::vector<Eigen::Vector3d> vertices;
    std::vector<std::array<int, 3>> triangles;
    for (std::size_t t = 0; t < s_.triangles.size(); ++t) {
      if (dead_[t]) continue;
      std::array<int, 3> tri;
      for (int q = 0; q < 3; ++q) {
        int& n = new_index[s_.triangles[t][q]];
        if (n < 0) {
          n = static_cast<int>(vertices.size());
          vertices.push_back(s_.vertices_mm[s_.triangles[t][q]]);
        }
        tri[q] = n;
      }
      triangles.push_back(tri);
    }
    s_.vertices_mm = std::move(vertices);
    s_.triangles = std::move(triangles);
  }

  TriSurface& s_;
  std::vector<std::vector<int>> vt_;
  std::vector<std::uint8_t> dead_;
};

// Neighbour lists (CSR) of the surface's vertex graph.
void vertex_neighbours(const TriSurface& s, std::vector<int>& start, std::vector<int>& nbr) {
  std::vector<std::pair<int, int>> edges;
  edges.reserve(s.triangles.size() * 6);
  for (const auto& t : s.triangles)
    for (int e = 0; e < 3; ++e) {
      edges.emplace_back(t[e], t[(e + 1) % 3]);
      edges.emplace_back(t[(e + 1) % 3], t[e]);
    }
  std::sort(edges.begin(), edges.end());
  edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
  start.assign(s.vertices_mm.size() + 1, 0);
  for (const auto& e : edges) ++start[e.first + 1];
  for (std::size_t v = 0; v < s.vertices_mm.size(); ++v) start[v + 1] += start[v];
  nbr.resize(edges.size());
  for (std::size_t e = 0; e < edges.size(); ++e) nbr[e] = edges[e].second;
}

void umbrella_step(std::vector<Eigen::Vector3d>& x, const std::vector<int>& start,
                   const std::vector<int>& nbr, double factor, std::vector<Eigen::Vector3d>& tmp) {
  tmp = x;
  for (std::size_t v = 0; v < x.size(); ++v) {
    const int n = start[v + 1] - start[v];
    if (n == 0) continue;
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    for (int e = start[v]; e < start[v + 1]; ++e) mean += tmp[nbr[e]];
    x[v] = tmp[v] + factor * (mean / n - tmp[v]);
  }
}

void taubin_smooth(TriSurface& s, const ModelParameters& p) {
  if (p.taubin_iterations == 0 || s.triangles.empty()) return;
  std::vector<int> start, nbr;
  vertex_neighbours(s, start, nbr);
  std::vector<Eigen::Vector3d> tmp;
  for (int it = 0; it < p.taubin_iterations; ++it) {
    umbrella_step(s.vertices_mm, start, nbr, p.taubin_lambda, tmp);
    umbrella_step(s.vertices_mm, start, nbr, p.taubin_mu, tmp);
  }
}

}  // namespace

TriSurface surface_model(const LabelImage& labels, const std::vector<std::uint16_t>& labels_in_structure,
                         const ModelParameters& params) {
  validate(labels, params);
  const auto sigma = sigma_voxels(labels.grid, params.presmooth_sigma_mm);
  Field field;
  if (!make_field(labels, labels_in_structure, sigma, field)) return {};
  for (int a = 0; a < 3; ++a) blur_axis(field, a, sigma[a]);
  TetContourer contourer(field);
  contourer.run();
  TriSurface surface = contourer.take(labels.grid);
  if (params.min_edge_fraction > 0)
    ShortEdgeCollapser(surface).run(params.min_edge_fraction * labels.grid.spacing_mm().minCoeff(), 3);
  taubin_smooth(surface, params);
  return surface;
}

TriSurface surface_model(const LabelImage& labels, std::uint16_t label, const ModelParameters& params) {
  return surface_model(labels, std::vector<std::uint16_t>{label}, params);
}

std::map<std::string, TriSurface> structure_models(const LabelImage& labels,
                                                   const std::vector<StructureDefinition>& table,
                                                   const ModelParameters& params) {
  std::map<std::string, TriSurface> models;
  for (const auto& def : table) {
    if (def.name.empty() || def.labels.empty())
      throw InputError("structure_models: every structure needs a name and at least one label");
    TriSurface s = surface_model(labels, def.labels, params);
    if (!s.triangles.empty()) models.emplace(def.name, std::move(s));
  }
  return models;
}

double surface_area_mm2(const TriSurface& s) {
  double area = 0;
  for (const auto& t : s.triangles)
    area += 0.5 * (s.vertices_mm[t[1]] - s.vertices_mm[t[0]]).cross(s.vertices_mm[t[2]] - s.vertices_mm[t[0]]).norm();
  return area;
}

bool is_closed_oriented_manifold(const TriSurface& s) {
  // Each directed edge must occur once and its reverse once.
  std::vector<std::pair<int, int>> directed;
  directed.reserve(s.triangles.size() * 3);
  for (const auto& t : s.triangles)
    for (int e = 0; e < 3; ++e) directed.emplace_back(t[e], t[(e + 1) % 3]);
  std::sort(directed.begin(), directed.end());
  for (std::size_t e = 0; e < directed.size(); ++e) {
    if (e + 1 < directed.size() && directed[e] == directed[e + 1]) return false;
    const std::pair<int, int> reverse{directed[e].second, directed[e].first};
    if (!std::binary_search(directed.begin(), directed.end(), reverse)) return false;
  }
  return !s.triangles.empty();
}

}  // namespace brainshift
