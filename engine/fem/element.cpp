#include "fem/element.h"

#include <string>

#include "core/errors.h"

namespace brainshift {

void validate_material(const Material& m) {
  if (!(m.youngs_modulus_pa > 0.0))
    throw InputError("material: Young's modulus must be > 0 Pa, got " +
                     std::to_string(m.youngs_modulus_pa));
  if (!(m.poisson_ratio > -1.0 && m.poisson_ratio < 0.5))
    throw InputError("material: Poisson ratio must be in (-1, 0.5), got " +
                     std::to_string(m.poisson_ratio));
}

Eigen::Matrix<double, 6, 6> elasticity_matrix(const Material& m) {
  validate_material(m);
  const double e = m.youngs_modulus_pa, nu = m.poisson_ratio;
  const double lambda = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
  const double mu = e / (2.0 * (1.0 + nu));
  Eigen::Matrix<double, 6, 6> d = Eigen::Matrix<double, 6, 6>::Zero();
  d.topLeftCorner<3, 3>().setConstant(lambda);
  d.topLeftCorner<3, 3>().diagonal().array() += 2.0 * mu;
  d.bottomRightCorner<3, 3>().diagonal().setConstant(mu);
  return d;
}

Eigen::Matrix<double, 12, 12> p1_element_stiffness(const std::array<Eigen::Vector3d, 4>& x,
                                                   const Material& material) {
  return p1_element_stiffness(x, elasticity_matrix(material));
}

Eigen::Matrix<double, 12, 12> p1_element_stiffness(const std::array<Eigen::Vector3d, 4>& x,
                                                   const Eigen::Matrix<double, 6, 6>& d) {
  Eigen::Matrix3d edges;  // columns: edges from node 0
  edges << x[1] - x[0], x[2] - x[0], x[3] - x[0];
  const double volume = edges.determinant() / 6.0;
  // Relative threshold: a sliver this flat has no usable gradient.
  const double scale = (x[1] - x[0]).norm() + (x[2] - x[0]).norm() + (x[3] - x[0]).norm();
  if (!(volume > 1e-12 * scale * scale * scale))
    throw InputError("tetrahedron is degenerate or inverted (volume " + std::to_string(volume) +
                     " mm^3)");
  // Rows of edges^-1 are the gradients of the barycentric coordinates 1..3.
  const Eigen::Matrix3d inv = edges.inverse();
  std::array<Eigen::Vector3d, 4> grad;
  for (int i = 0; i < 3; ++i) grad[i + 1] = inv.row(i).transpose();
  grad[0] = -(grad[1] + grad[2] + grad[3]);

  Eigen::Matrix<double, 6, 12> b = Eigen::Matrix<double, 6, 12>::Zero();
  for (int n = 0; n < 4; ++n) {
    const Eigen::Vector3d& g = grad[n];
    const int c = 3 * n;
    b(0, c) = g.x();
    b(1, c + 1) = g.y();
    b(2, c + 2) = g.z();
    b(3, c + 1) = g.z();
    b(3, c + 2) = g.y();
    b(4, c) = g.z();
    b(4, c + 2) = g.x();
    b(5, c) = g.y();
    b(5, c + 1) = g.x();
  }
  Eigen::Matrix<double, 12, 12> k = volume * b.transpose() * d * b;
  // Exact symmetry matters: CHOLMOD/MUMPS Cholesky read one triangle only.
  return 0.5 * (k + k.transpose());
}

std::vector<Eigen::Vector3d> consistent_nodal_loads(const TetMesh& mesh,
                                                    const std::vector<Eigen::Vector3d>& density) {
  if (density.size() != mesh.node_count())
    throw InputError("consistent_nodal_loads: " + std::to_string(density.size()) +
                     " force densities for " + std::to_string(mesh.node_count()) + " nodes");
  std::vector<Eigen::Vector3d> loads(mesh.node_count(), Eigen::Vector3d::Zero());
  for (std::size_t t = 0; t < mesh.tet_count(); ++t) {
    const auto& n = mesh.tets[t];
    const double v = tet_volume_mm3(mesh, t);
    const Eigen::Vector3d sum = density[n[0]] + density[n[1]] + density[n[2]] + density[n[3]];
    for (int i : n) loads[i] += v / 20.0 * (sum + density[i]);
  }
  return loads;
}

}  // namespace brainshift
