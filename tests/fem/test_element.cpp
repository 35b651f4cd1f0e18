// Element-level checks of the P1 elastic stiffness and the consistent load.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <random>

#include "box_mesh.h"
#include "core/errors.h"
#include "fem/element.h"

namespace brainshift {
namespace {

// Random but well-shaped: a perturbed regular-ish tet, rotated and shifted.
std::array<Eigen::Vector3d, 4> random_tet(std::mt19937& rng) {
  std::uniform_real_distribution<double> jitter(-0.2, 0.2), shift(-50, 50);
  std::array<Eigen::Vector3d, 4> x{Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(2, 0, 0),
                                   Eigen::Vector3d(1, 1.7, 0), Eigen::Vector3d(1, 0.6, 1.6)};
  const Eigen::Matrix3d rot =
      Eigen::Quaterniond(Eigen::Vector4d::Random().normalized()).toRotationMatrix();
  const Eigen::Vector3d offset(shift(rng), shift(rng), shift(rng));
  for (auto& p : x) p = rot * (p + Eigen::Vector3d(jitter(rng), jitter(rng), jitter(rng))) + offset;
  if ((x[1] - x[0]).dot((x[2] - x[0]).cross(x[3] - x[0])) < 0) std::swap(x[2], x[3]);
  return x;
}

Eigen::Matrix<double, 12, 1> rigid_mode(const std::array<Eigen::Vector3d, 4>& x, int mode) {
  Eigen::Matrix<double, 12, 1> u;
  for (int n = 0; n < 4; ++n) {
    Eigen::Vector3d d = Eigen::Vector3d::Zero();
    if (mode < 3) d[mode] = 1.0;                                  // translation
    else d = Eigen::Vector3d::Unit(mode - 3).cross(x[n]);         // infinitesimal rotation
    u.segment<3>(3 * n) = d;
  }
  return u;
}

TEST(ElementStiffness, SymmetricPsdWithExactlySixRigidModes) {
  std::mt19937 rng(42);
  const Material material{3000.0, 0.45};
  for (int trial = 0; trial < 5; ++trial) {
    const auto x = random_tet(rng);
    const Eigen::Matrix<double, 12, 12> k = p1_element_stiffness(x, material);
    EXPECT_LT((k - k.transpose()).norm(), 1e-12 * k.norm());
    const Eigen::Matrix<double, 12, 1> ev = Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 12, 12>>(k).eigenvalues();
    const double tol = 1e-10 * ev.maxCoeff();
    int zeros = 0;
    for (int i = 0; i < 12; ++i) {
      EXPECT_GT(ev[i], -tol) << "negative eigenvalue " << ev[i];
      if (std::abs(ev[i]) < tol) ++zeros;
    }
    EXPECT_EQ(zeros, 6);
    for (int mode = 0; mode < 6; ++mode) {
      const Eigen::Matrix<double, 12, 1> u = rigid_mode(x, mode);
      EXPECT_LT((k * u).norm(), 1e-10 * k.norm() * u.norm()) << "mode " << mode;
    }
  }
}

TEST(ElementStiffness, UniaxialStrainEnergyMatchesContinuum) {
  // Strain energy 1/2 u^T K u of an affine field equals V * 1/2 eps:D:eps exactly.
  std::mt19937 rng(7);
  const Material material{5000.0, 0.3};
  const auto x = random_tet(rng);
  const double e = 0.01;  // u_x = e * x  ->  eps_xx = e
  Eigen::Matrix<double, 12, 1> u = Eigen::Matrix<double, 12, 1>::Zero();
  for (int n = 0; n < 4; ++n) u[3 * n] = e * x[n].x();
  const double volume = (x[1] - x[0]).dot((x[2] - x[0]).cross(x[3] - x[0])) / 6.0;
  const double nu = material.poisson_ratio;
  const double lambda_plus_2mu = material.youngs_modulus_pa * (1 - nu) / ((1 + nu) * (1 - 2 * nu));
  const double expected = 0.5 * volume * lambda_plus_2mu * e * e;
  const double energy = 0.5 * u.dot(p1_element_stiffness(x, material) * u);
  EXPECT_NEAR(energy, expected, 1e-12 * expected);
}

TEST(ElementStiffness, RejectsBadInput) {
  const std::array<Eigen::Vector3d, 4> flat{Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(1, 0, 0),
                                            Eigen::Vector3d(0, 1, 0), Eigen::Vector3d(1, 1, 0)};
  EXPECT_THROW(p1_element_stiffness(flat, Material{}), InputError);
  std::array<Eigen::Vector3d, 4> inverted{Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(1, 0, 0),
                                          Eigen::Vector3d(0, 0, 1), Eigen::Vector3d(0, 1, 0)};
  EXPECT_THROW(p1_element_stiffness(inverted, Material{}), InputError);
  std::swap(inverted[2], inverted[3]);
  EXPECT_NO_THROW(p1_element_stiffness(inverted, Material{}));
  EXPECT_THROW(p1_element_stiffness(inverted, Material{3000, 0.5}), InputError);
  EXPECT_THROW(p1_element_stiffness(inverted, Material{0, 0.3}), InputError);
}

TEST(ConsistentLoad, IntegratesLinearDensityExactly) {
  // Total force = integral of b; for b linear in x, P1 interpolation is exact.
  const auto box = test::make_box_mesh({3, 2, 4}, Eigen::Vector3d(1, 2, 3), Eigen::Vector3d(3, 2, 2));
  std::vector<Eigen::Vector3d> density;
  for (const auto& p : box.mesh.nodes_mm) density.emplace_back(2.0, p.x(), 0.0);
  Eigen::Vector3d total = Eigen::Vector3d::Zero();
  for (const auto& f : consistent_nodal_loads(box.mesh, density)) total += f;
  const double volume = 3 * 2 * 2, mean_x = 1 + 1.5;
  EXPECT_NEAR(total.x(), 2.0 * volume, 1e-12 * volume);
  EXPECT_NEAR(total.y(), mean_x * volume, 1e-12 * volume);
  EXPECT_NEAR(total.z(), 0.0, 1e-12);
  EXPECT_THROW(consistent_nodal_loads(box.mesh, {}), InputError);
}

TEST(BoxMesh, IsConformingWithPositiveVolumes) {
  const auto box = test::make_box_mesh({3, 4, 5}, Eigen::Vector3d::Zero(), Eigen::Vector3d(3, 4, 5));
  double total = 0;
  for (std::size_t t = 0; t < box.mesh.tet_count(); ++t) {
    ASSERT_GT(tet_volume_mm3(box.mesh, t), 0.0);
    total += tet_volume_mm3(box.mesh, t);
  }
  EXPECT_NEAR(total, 60.0, 1e-10);
  EXPECT_EQ(box.interior_nodes.size(), 2u * 3u * 4u);
}

}  // namespace
}  // namespace brainshift
