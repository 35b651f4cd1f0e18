// ElasticModel end-to-end checks. Runs under mpirun at np 1 and np 2: every
// rank executes every test; results are gathered to all ranks, so the
// assertions see identical data everywhere and no rank leaves a collective early.
#include <gtest/gtest.h>
#include <mpi.h>

#include <cmath>
#include <cstdio>
#include <functional>
#include <stdexcept>

#include "box_mesh.h"
#include "core/errors.h"
#include "fem/elastic_model.h"
#include "fem/petsc_session.h"

namespace brainshift {
namespace {

using Field = std::vector<Eigen::Vector3d>;

struct Combo {
  SolverKind solver;
  DirichletMethod dirichlet;
};
// Every valid combination (cg_gamg needs the symmetric reduced system).
const Combo kCombos[] = {
    {SolverKind::direct_cholesky, DirichletMethod::symmetric_elimination},
    {SolverKind::direct_cholesky, DirichletMethod::row_replacement},
    {SolverKind::cg_gamg, DirichletMethod::symmetric_elimination},
    {SolverKind::gmres_bjacobi, DirichletMethod::symmetric_elimination},
    {SolverKind::gmres_bjacobi, DirichletMethod::row_replacement},
};

std::string name(const Combo& c) {
  return std::string(to_string(c.solver)) + " / " + to_string(c.dirichlet);
}

constexpr double kPatchNu = 0.45;

// Stiffness ratio 4 between the two halves of the box; same nu so that the
// affine patch-test field stays an exact solution (see affine()).
ElasticOptions two_materials(Combo c, double rtol = 1e-12) {
  ElasticOptions o;
  o.material_by_label = {{1, Material{3000.0, kPatchNu}}, {2, Material{12000.0, kPatchNu}}};
  o.solver = c.solver;
  o.dirichlet = c.dirichlet;
  o.rtol = rtol;
  return o;
}

Field values_at(const TetMesh& mesh, const std::vector<int>& nodes,
                const std::function<Eigen::Vector3d(const Eigen::Vector3d&)>& u) {
  Field out;
  for (int v : nodes) out.push_back(u(mesh.nodes_mm[v]));
  return out;
}

// The two labels of the box meet at a plane x = const. An affine field is an
// exact solution of the bimaterial problem only if the traction on that plane
// is continuous; with equal nu and different E this holds when sigma_xx =
// sigma_xy = sigma_xz = 0: eps_xy = eps_xz = 0 and eps_xx = -nu/(1-nu)(eps_yy + eps_zz).
// Any rotation (skew part) and translation may be added.
Eigen::Vector3d affine(const Eigen::Vector3d& x) {
  const double eyy = 0.012, ezz = -0.004, eyz = 0.006;
  Eigen::Matrix3d strain;
  strain << -kPatchNu / (1 - kPatchNu) * (eyy + ezz), 0, 0, 0, eyy, eyz, 0, eyz, ezz;
  Eigen::Matrix3d rotation;  // infinitesimal, skew-symmetric
  rotation << 0, -0.01, 0.02, 0.01, 0, -0.015, -0.02, 0.015, 0;
  return (strain + rotation) * x + Eigen::Vector3d(0.5, -0.3, 0.2);
}

Eigen::Vector3d wavy(const Eigen::Vector3d& x) {
  return Eigen::Vector3d(0.3 * std::sin(0.4 * x.x()) * std::cos(0.3 * x.y()),
                         0.2 * std::cos(0.5 * x.z()) + 0.01 * x.x() * x.y(), 0.15 * std::sin(0.3 * x.y() + 0.2 * x.z()));
}

double max_norm(const Field& f) {
  double m = 0;
  for (const auto& v : f) m = std::max(m, v.norm());
  return m;
}

double max_diff(const Field& a, const Field& b, const std::vector<int>& nodes) {
  double m = 0;
  for (int v : nodes) m = std::max(m, (a[v] - b[v]).norm());
  return m;
}

Field solve_once(MPI_Comm comm, const test::BoxMesh& box, ElasticOptions o, const Field& values,
                 SolveReport* report = nullptr) {
  ElasticModel model(comm, box.mesh, box.boundary_nodes, std::move(o));
  model.assemble();
  model.setup_solver();
  Field u;
  const SolveReport r = model.solve(values, u);
  if (report) *report = r;
  return u;
}

TEST(ElasticModel, PatchTestReproducesAffineFieldForEverySolver) {
  const auto box = test::make_box_mesh({5, 4, 4}, Eigen::Vector3d(-2, 1, 3), Eigen::Vector3d(10, 8, 8));
  const Field values = values_at(box.mesh, box.boundary_nodes, affine);
  for (const Combo& c : kCombos) {
    SolveReport report;
    const Field u = solve_once(MPI_COMM_WORLD, box, two_materials(c), values, &report);
    double worst = 0;
    for (int v : box.interior_nodes) worst = std::max(worst, (u[v] - affine(box.mesh.nodes_mm[v])).norm());
    EXPECT_LT(worst, 1e-9 * max_norm(values)) << name(c) << ": " << report.solver_description;
    EXPECT_LT(report.relative_residual, 1e-10) << name(c);
    // Fixed nodes come back as given (row replacement solves for them too).
    for (std::size_t i = 0; i < box.boundary_nodes.size(); ++i)
      ASSERT_LT((u[box.boundary_nodes[i]] - values[i]).norm(), 1e-9 * max_norm(values)) << name(c);
  }
}

// Manufactured solution u = c * s(x), s = sin(a(x+px)) sin(a(y+py)) sin(a(z+pz)),
// with body force f = -div sigma(u) = -(mu lap u + (lambda + mu) grad div u).
struct Manufactured {
  double a = 2.0;
  Eigen::Vector3d phase{0.3, 0.2, 0.1}, c{0.05, 0.1, -0.07};
  Material material{3000.0, 0.3};

  Eigen::Vector3d u(const Eigen::Vector3d& x) const { return c * s(x); }
  double s(const Eigen::Vector3d& x) const {
    const Eigen::Vector3d t = a * (x + phase);
    return std::sin(t.x()) * std::sin(t.y()) * std::sin(t.z());
  }
  Eigen::Vector3d force(const Eigen::Vector3d& x) const {
    const Eigen::Vector3d t = a * (x + phase);
    const Eigen::Vector3d sn = t.array().sin(), cs = t.array().cos();
    Eigen::Matrix3d hessian;
    hessian << -sn.x() * sn.y() * sn.z(), cs.x() * cs.y() * sn.z(), cs.x() * sn.y() * cs.z(),
        cs.x() * cs.y() * sn.z(), -sn.x() * sn.y() * sn.z(), sn.x() * cs.y() * cs.z(),
        cs.x() * sn.y() * cs.z(), sn.x() * cs.y() * cs.z(), -sn.x() * sn.y() * sn.z();
    hessian *= a * a;
    const double e = material.youngs_modulus_pa, nu = material.poisson_ratio;
    const double lambda = e * nu / ((1 + nu) * (1 - 2 * nu)), mu = e / (2 * (1 + nu));
    const Eigen::Vector3d laplacian_u = c * hessian.trace();
    return -(mu * laplacian_u + (lambda + mu) * hessian * c);
  }
};

TEST(ElasticModel, ManufacturedSolutionConvergesAtSecondOrder) {
  const Manufactured exact;
  std::vector<double> errors;
  for (int cells : {4, 8, 16}) {
    const auto box = test::make_box_mesh({cells, cells, cells}, Eigen::Vector3d::Zero(), Eigen::Vector3d(1, 1, 1));
    ElasticOptions o;
    o.default_material = exact.material;
    ElasticModel model(MPI_COMM_WORLD, box.mesh, box.boundary_nodes, o);
    model.assemble();
    model.setup_solver();
    Field density;
    for (const auto& x : box.mesh.nodes_mm) density.push_back(exact.force(x));
    Field u;
    model.solve(values_at(box.mesh, box.boundary_nodes, [&](const Eigen::Vector3d& x) { return exact.u(x); }),
                consistent_nodal_loads(box.mesh, density), u);
    double sum_sq = 0;
    for (int v : box.interior_nodes) sum_sq += (u[v] - exact.u(box.mesh.nodes_mm[v])).squaredNorm();
    errors.push_back(std::sqrt(sum_sq / box.interior_nodes.size()));
  }
  for (std::size_t i = 1; i < errors.size(); ++i) {
    const double rate = std::log2(errors[i - 1] / errors[i]);
    EXPECT_GT(rate, 1.7) << "RMS nodal errors " << errors[i - 1] << " -> " << errors[i];
  }
  // Sanity bound on the finest level (measured 1.7e-3 relative at h = 1/16).
  EXPECT_LT(errors.back(), 3e-3 * exact.c.norm());
  std::printf("manufactured RMS nodal errors: %.3e %.3e %.3e\n", errors[0], errors[1], errors[2]);
}

TEST(ElasticModel, AllSolversAndDirichletMethodsAgree) {
  const auto box = test::make_box_mesh({6, 5, 5}, Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(12, 10, 10));
  const Field values = values_at(box.mesh, box.boundary_nodes, wavy);
  const Field reference = solve_once(MPI_COMM_WORLD, box, two_materials(kCombos[0]), values);
  const double scale = max_norm(reference);
  ASSERT_GT(scale, 0.1);
  for (const Combo& c : kCombos) {
    const Field u = solve_once(MPI_COMM_WORLD, box, two_materials(c, 1e-10), values);
    EXPECT_LT(max_diff(u, reference, box.interior_nodes), 1e-6 * scale) << name(c);
  }
  // The wavy boundary field is not affine: the interior must actually differ
  // from the affine interpolation, or this test would prove nothing.
  EXPECT_GT(max_diff(reference, Field(reference.size(), Eigen::Vector3d::Zero()), box.interior_nodes), 0.01);
}

TEST(ElasticModel, DistributedSolveMatchesSerialSolve) {
  int rank = 0;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank);
  const auto box = test::make_box_mesh({8, 6, 6}, Eigen::Vector3d(5, 5, 5), Eigen::Vector3d(16, 12, 12));
  const Field values = values_at(box.mesh, box.boundary_nodes, wavy);
  const Combo direct{SolverKind::direct_cholesky, DirichletMethod::symmetric_elimination};
  std::vector<double> serial(3 * box.mesh.node_count());
  if (rank == 0) {
    const Field u = solve_once(MPI_COMM_SELF, box, two_materials(direct), values);
    for (std::size_t v = 0; v < u.size(); ++v)
      for (int c = 0; c < 3; ++c) serial[3 * v + c] = u[v][c];
  }
  MPI_Bcast(serial.data(), static_cast<int>(serial.size()), MPI_DOUBLE, 0, MPI_COMM_WORLD);
  Field reference(box.mesh.node_count());
  for (std::size_t v = 0; v < reference.size(); ++v) reference[v] = Eigen::Map<Eigen::Vector3d>(&serial[3 * v]);
  const double scale = max_norm(reference);

  for (const std::string package : {"cholmod", "mumps"}) {
    ElasticOptions o = two_materials(direct);
    o.direct_package = package;
    const Field u = solve_once(MPI_COMM_WORLD, box, o, values);
    EXPECT_LT(max_diff(u, reference, box.interior_nodes), 1e-8 * scale) << package;
  }
  const Field iterative = solve_once(MPI_COMM_WORLD, box, two_materials({SolverKind::cg_gamg, DirichletMethod::symmetric_elimination}, 1e-13), values);
  EXPECT_LT(max_diff(iterative, reference, box.interior_nodes), 1e-8 * scale) << "cg_gamg";
}

TEST(ElasticModel, OwnershipRangesTileTheNodes) {
  const auto box = test::make_box_mesh({4, 3, 3}, Eigen::Vector3d::Zero(), Eigen::Vector3d(4, 3, 3));
  ElasticModel model(MPI_COMM_WORLD, box.mesh, box.boundary_nodes, ElasticOptions{});
  int size = 1;
  MPI_Comm_size(MPI_COMM_WORLD, &size);
  const auto [begin, end] = model.owned_nodes();
  std::vector<int> ranges(2 * size);
  const int mine[2] = {begin, end};
  MPI_Allgather(mine, 2, MPI_INT, ranges.data(), 2, MPI_INT, MPI_COMM_WORLD);
  EXPECT_EQ(ranges.front(), 0);
  EXPECT_EQ(ranges.back(), static_cast<int>(box.mesh.node_count()));
  for (int r = 1; r < size; ++r) EXPECT_EQ(ranges[2 * r], ranges[2 * r - 1]);
}

TEST(ElasticModel, NewBoundaryValuesReuseTheFactorisation) {
  const auto box = test::make_box_mesh({6, 6, 6}, Eigen::Vector3d::Zero(), Eigen::Vector3d(12, 12, 12));
  for (const Combo& c : {kCombos[0], kCombos[1], kCombos[2]}) {
    ElasticModel model(MPI_COMM_WORLD, box.mesh, box.boundary_nodes, two_materials(c));
    model.assemble();
    model.setup_solver();
    EXPECT_EQ(model.factorisation_count(), 1);
    Field first, second, again;
    model.solve(values_at(box.mesh, box.boundary_nodes, wavy), first);
    model.solve(values_at(box.mesh, box.boundary_nodes, affine), second);
    model.solve(values_at(box.mesh, box.boundary_nodes, wavy), again);
    EXPECT_EQ(model.factorisation_count(), 1) << name(c);
    double worst = 0;
    for (int v : box.interior_nodes) worst = std::max(worst, (second[v] - affine(box.mesh.nodes_mm[v])).norm());
    EXPECT_LT(worst, 1e-9 * max_norm(second)) << name(c);
    EXPECT_LT(max_diff(first, again, box.interior_nodes), 1e-9 * max_norm(first)) << name(c);
  }
}

TEST(ElasticModel, NonConvergenceThrowsWithPetscReason) {
  const auto box = test::make_box_mesh({6, 6, 6}, Eigen::Vector3d::Zero(), Eigen::Vector3d(12, 12, 12));
  const Field values = values_at(box.mesh, box.boundary_nodes, wavy);
  ElasticOptions o = two_materials({SolverKind::cg_gamg, DirichletMethod::symmetric_elimination});
  o.petsc_options = "-fem_ksp_max_it 2";
  try {
    solve_once(MPI_COMM_WORLD, box, o, values);
    ADD_FAILURE() << "expected ComputeError";
  } catch (const ComputeError& e) {
    EXPECT_NE(std::string(e.what()).find("DIVERGED_ITS"), std::string::npos) << e.what();
  }
  // The option lived in the model's private database: a new model converges.
  o.petsc_options.clear();
  EXPECT_NO_THROW(solve_once(MPI_COMM_WORLD, box, o, values));
}

TEST(ElasticModel, RejectsInvalidInput) {
  const auto box = test::make_box_mesh({3, 3, 3}, Eigen::Vector3d::Zero(), Eigen::Vector3d(3, 3, 3));
  const TetMesh& mesh = box.mesh;
  auto make = [&](std::vector<int> fixed, ElasticOptions o) { ElasticModel m(MPI_COMM_WORLD, mesh, std::move(fixed), std::move(o)); };
  EXPECT_THROW(make({0, 1, 2, 999999}, {}), InputError);
  EXPECT_THROW(make({0, 5, 5, 20}, {}), InputError);
  EXPECT_THROW(make({0, 1, 2, 3}, {}), InputError);  // collinear: one edge of the box
  ElasticOptions bad;
  bad.solver = SolverKind::cg_gamg;
  bad.dirichlet = DirichletMethod::row_replacement;
  EXPECT_THROW(make(box.boundary_nodes, bad), InputError);
  bad = {};
  bad.direct_package = "pardiso";
  EXPECT_THROW(make(box.boundary_nodes, bad), InputError);
  bad = {};
  bad.material_by_label[1] = Material{3000, 0.5};
  EXPECT_THROW(make(box.boundary_nodes, bad), InputError);

  ElasticModel model(MPI_COMM_WORLD, mesh, box.boundary_nodes, {});
  Field u;
  EXPECT_THROW(model.solve(Field(box.boundary_nodes.size()), u), std::logic_error);
  model.assemble();
  model.setup_solver();
  EXPECT_THROW(model.solve(Field(3), u), InputError);
}

}  // namespace
}  // namespace brainshift

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  MPI_Init(&argc, &argv);
  int status = 0;
  {
    brainshift::PetscSession petsc;
    status = RUN_ALL_TESTS();
  }
  MPI_Finalize();
  return status;
}
