#pragma once
// Linear (P1) tetrahedral elements for small-strain isotropic linear elasticity.
//
// Units: lengths in mm, moduli in Pa. The stiffness K = V * B^T D B then has
// units Pa*mm, so K * u[mm] is a force in Pa*mm^2 (= 1e-6 N = micronewton).
// Body-force densities are in Pa/mm (force per volume, consistent with that).
// With every boundary node prescribed and no body force the displacement does
// not depend on E at all, only on nu and on modulus ratios between labels.
#include <Eigen/Dense>
#include <array>
#include <vector>

#include "core/tet_mesh.h"

namespace brainshift {

struct Material {
  double youngs_modulus_pa = 3000.0;  // brain tissue is of order 1-10 kPa
  double poisson_ratio = 0.45;        // nearly incompressible; must stay < 0.5
};

// Throws InputError unless E > 0 and -1 < nu < 0.5 (nu = 0.5 makes lambda infinite).
void validate_material(const Material& material);

// Isotropic elasticity matrix in Voigt order (xx, yy, zz, yz, xz, xy) with
// engineering shear strains.
Eigen::Matrix<double, 6, 6> elasticity_matrix(const Material& material);

// 12x12 element stiffness, dofs ordered node-major (n0x n0y n0z n1x ...).
// Throws InputError for a degenerate or inverted tet (volume <= 0): the mesher
// guarantees positive orientation, so anything else is corrupt input.
Eigen::Matrix<double, 12, 12> p1_element_stiffness(const std::array<Eigen::Vector3d, 4>& nodes_mm,
                                                   const Material& material);

// Same with a precomputed elasticity_matrix(): assembly computes D once per
// label instead of once per tet.
Eigen::Matrix<double, 12, 12> p1_element_stiffness(const std::array<Eigen::Vector3d, 4>& nodes_mm,
                                                   const Eigen::Matrix<double, 6, 6>& elasticity);

// Consistent nodal loads M * b for a body-force density b given at the nodes
// (P1 interpolated): per tet M_ij = V/20 (1 + delta_ij). Using the consistent
// mass matrix (not a lumped one) keeps the load second-order accurate.
// Returns one force (Pa*mm^2) per mesh node.
std::vector<Eigen::Vector3d> consistent_nodal_loads(
    const TetMesh& mesh, const std::vector<Eigen::Vector3d>& force_density_pa_per_mm);

}  // namespace brainshift
