// The phantom generator: its truth must be invertible, deterministic, have
// the requested magnitudes, and its images/labels/landmarks must agree with
// its own field (otherwise every accuracy number built on it is wrong).
#include <gtest/gtest.h>

#include <cmath>

#include "core/errors.h"
#include "image/resample.h"
#include "phantom/brain_shift_phantom.h"
#include "phantom/phantom_artefacts.h"

namespace brainshift {
namespace {

bool in_ellipsoid(const Eigen::Vector3d& p, const Eigen::Vector3d& c, const Eigen::Vector3d& axes) {
  return (p - c).cwiseQuotient(axes).squaredNorm() <= 1.0;
}

// A synthetic head: ellipsoidal brain (1), two ventricles (2), two
// corticospinal tracts (3), a skull shell in the T1 only; textured T1.
struct Preop {
  ImageF t1;
  LabelImage labels;
};

const Preop& synthetic_preop() {
  static const Preop preop = [] {
    Grid3 g;
    g.dims = {100, 120, 96};
    const double h = 1.5;
    g.world_from_voxel = Eigen::Vector4d(h, h, h, 1).asDiagonal();
    g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-74.25, -89.25, -71.25);
    Preop p{ImageF(g, 0.f), LabelImage(g, 0)};
    const Eigen::Vector3d brain_axes(60, 75, 55);
    for (int k = 0; k < g.dims[2]; ++k)
      for (int j = 0; j < g.dims[1]; ++j)
        for (int i = 0; i < g.dims[0]; ++i) {
          const Eigen::Vector3d x = g.world_mm(i, j, k);
          const double r = x.cwiseQuotient(brain_axes).norm();
          float t1 = 0;
          std::uint16_t l = 0;
          if (r <= 1.0) {
            l = 1;
            t1 = static_cast<float>(100 + 20 * std::sin(x.x() / 7) * std::sin(x.y() / 9) * std::sin(x.z() / 8));
            for (double side : {-1.0, 1.0}) {
              if (in_ellipsoid(x, Eigen::Vector3d(12 * side, 0, 10), Eigen::Vector3d(6, 20, 8))) l = 2;
              const Eigen::Vector2d off(x.x() - 15 * side, x.y() + 10);
              if (l == 1 && off.norm() < 4 && x.z() > -50 && x.z() < 20) l = 3;
            }
            if (l == 2) t1 = 20;
          } else if (r > 1.08 && r < 1.18) {
            t1 = 60;  // skull
          }
          p.t1.at(i, j, k) = t1;
          p.labels.at(i, j, k) = l;
        }
    return p;
  }();
  return preop;
}

PhantomSpec small_spec(const std::string& name) {
  PhantomSpec s;
  s.name = name;
  s.dims = {96, 96, 48};
  s.spacing_mm = {2, 2, 3.5};
  s.sinking.craniotomy_direction = {-0.5, 0.7, 0.5};
  s.sinking.cortex_mm = 12;
  s.sinking.deep_mm = 2;
  return s;
}

Eigen::Vector3d sample_field(const VectorImage3& u, const Eigen::Vector3d& x) {
  Eigen::Vector3d out;
  for (int c = 0; c < 3; ++c) {
    ImageF comp(u.grid);
    for (std::size_t v = 0; v < comp.voxels.size(); ++v) comp.voxels[v] = u.vectors[v][c];
    out[c] = sample_linear(comp, x, 0.f);
  }
  return out;
}

double dice(const LabelImage& a, const LabelImage& b, std::uint16_t label) {
  std::size_t both = 0, na = 0, nb = 0;
  for (std::size_t v = 0; v < a.voxels.size(); ++v) {
    const bool ia = a.voxels[v] == label, ib = b.voxels[v] == label;
    both += ia && ib;
    na += ia;
    nb += ib;
  }
  return 2.0 * both / static_cast<double>(na + nb);
}

// Preop labels pulled back by the true field, merged to the intraop label set.
LabelImage warp_labels(const LabelImage& preop, const VectorImage3& u) {
  LabelImage out(u.grid, 0);
  const auto& d = u.grid.dims;
  for (int k = 0; k < d[2]; ++k)
    for (int j = 0; j < d[1]; ++j)
      for (int i = 0; i < d[0]; ++i) {
        const std::size_t v = u.grid.index(i, j, k);
        const std::uint16_t l = sample_nearest(preop, u.grid.world_mm(i, j, k) + u.vectors[v].cast<double>(), 0);
        out.voxels[v] = l == 0 ? 0 : l == 2 ? 2 : 1;
      }
  return out;
}

TEST(Phantom, DeterministicForASeed) {
  const auto& pre = synthetic_preop();
  const PhantomSpec s = small_spec("det");
  const PhantomCase a = make_phantom(pre.t1, pre.labels, s);
  const PhantomCase b = make_phantom(pre.t1, pre.labels, s);
  EXPECT_EQ(a.intraop_t1.voxels, b.intraop_t1.voxels);
  EXPECT_EQ(a.intraop_labels.voxels, b.intraop_labels.voxels);
  ASSERT_EQ(a.landmarks_intraop_preop_mm.size(), b.landmarks_intraop_preop_mm.size());
  for (std::size_t l = 0; l < a.landmarks_intraop_preop_mm.size(); ++l)
    EXPECT_EQ(a.landmarks_intraop_preop_mm[l].first, b.landmarks_intraop_preop_mm[l].first);
  PhantomSpec other = s;
  other.seed = 99;
  const PhantomCase c = make_phantom(pre.t1, pre.labels, other);
  EXPECT_NE(a.intraop_t1.voxels, c.intraop_t1.voxels);
  EXPECT_NE(a.intraop_labels.voxels, c.intraop_labels.voxels);
}

TEST(Phantom, SinkingMagnitudesAtTheCraniotomyAndDeep) {
  const auto& pre = synthetic_preop();
  PhantomSpec s = small_spec("sink");
  const PhantomDeformation phi(pre.labels, s);
  const Eigen::Vector3d c = phi.craniotomy_mm();
  // On the brain surface (ellipsoid radius 1) along the requested direction.
  EXPECT_NEAR(c.cwiseQuotient(Eigen::Vector3d(60, 75, 55)).norm(), 1.0, 0.03);
  EXPECT_NEAR((phi.forward(c) - c).norm(), 12.0, 1e-6);
  const Eigen::Vector3d deep = c + 70 * phi.gravity();
  EXPECT_LT((phi.forward(deep) - deep).norm(), 2.0 + 0.2);
  EXPECT_GT((phi.forward(deep) - deep).norm(), 1.0);
  // The far side of the brain rests on the skull.
  const Eigen::Vector3d far = c + phi.brain_depth_along_gravity_mm() * phi.gravity();
  EXPECT_LT((phi.forward(far) - far).norm(), 0.1);
  // Cortex far from the craniotomy axis hardly moves (lateral fade).
  const Eigen::Vector3d lateral(58, -20, -10);
  EXPECT_LT((phi.forward(lateral) - lateral).norm(), 0.15 * 12);

  const PhantomCase pc = make_phantom(pre.t1, pre.labels, s);
  EXPECT_DOUBLE_EQ(pc.description["nonrigid_scale_applied"].get<double>(), 1.0);
  // The field at the sunken cortex points back to the preop cortex.
  const Eigen::Vector3d x = phi.forward(c);
  EXPECT_LT((x + sample_field(pc.true_pullback_mm, x) - c).norm(), 0.3);
}

TEST(Phantom, InverseIsExactAndJacobianBoundedForTheSuite) {
  const auto& pre = synthetic_preop();
  for (PhantomSpec s : standard_phantom_suite()) {
    SCOPED_TRACE(s.name);
    s.dims = {96, 96, 48};
    s.spacing_mm = {2, 2, 3.5};
    const PhantomCase pc = make_phantom(pre.t1, pre.labels, s);
    EXPECT_GT(min_jacobian_determinant(pc.true_pullback_mm), 0.2);
    EXPECT_GT(pc.description["min_jacobian"].get<double>(), 0.2);
    const PhantomDeformation phi(pre.labels, s);
    ASSERT_EQ(pc.landmarks_intraop_preop_mm.size(), 200u);
    for (const auto& [x, p] : pc.landmarks_intraop_preop_mm) {
      EXPECT_LT((phi.forward(p) - x).norm(), 1e-4);  // the pair is exact
      EXPECT_LT((x + sample_field(pc.true_pullback_mm, x) - p).norm(), 0.3);  // and agrees with the field
      EXPECT_NE(sample_nearest(pre.labels, p, 0), 0);  // inside the preop brain
    }
  }
}

TEST(Phantom, SuiteIsVaried) {
  const auto suite = standard_phantom_suite();
  ASSERT_GE(suite.size(), 6u);
  int resections = 0, swellings = 0, rigid = 0, oblique = 0;
  for (const auto& s : suite) {
    resections += s.resection.enabled;
    swellings += s.swelling.enabled;
    rigid += s.rigid.rotation_deg.norm() > 0;
    oblique += s.oblique_deg.norm() > 0;
    EXPECT_EQ(s.dims, (std::array<int, 3>{256, 256, 60}));
  }
  EXPECT_GE(resections, 1);
  EXPECT_GE(swellings, 1);
  EXPECT_GE(rigid, 2);
  EXPECT_GE(oblique, 1);
}

TEST(Phantom, LabelsMatchTheWarpedPreopLabels) {
  const auto& pre = synthetic_preop();
  PhantomSpec s = small_spec("labels");
  s.label_noise_mm = 0;
  const PhantomCase clean = make_phantom(pre.t1, pre.labels, s);
  const LabelImage warped = warp_labels(pre.labels, clean.true_pullback_mm);
  EXPECT_GT(dice(clean.intraop_labels, warped, 1), 0.97);
  EXPECT_GT(dice(clean.intraop_labels, warped, 2), 0.9);
  // With ~1 mm of correlated boundary noise the match degrades only a little.
  s.label_noise_mm = 1.0;
  const PhantomCase noisy = make_phantom(pre.t1, pre.labels, s);
  const double d1 = dice(noisy.intraop_labels, warped, 1);
  EXPECT_GT(d1, 0.95);
  EXPECT_LT(d1, dice(clean.intraop_labels, warped, 1));
  for (auto l : noisy.intraop_labels.voxels) EXPECT_LE(l, 2);
}

TEST(Phantom, RigidOnlyFieldIsTheInverseRigidMap) {
  const auto& pre = synthetic_preop();
  PhantomSpec s = small_spec("rigid");
  s.sinking.enabled = false;
  s.rigid.rotation_deg = {4, -3, 5};
  s.rigid.translation_mm = {3, -2, 4};
  s.noise_fraction = 0;
  s.bias_amplitude = 0;
  const PhantomCase pc = make_phantom(pre.t1, pre.labels, s);
  const Eigen::Matrix4d back = pc.true_intraop_from_preop_rigid.inverse();
  const Grid3& g = pc.true_pullback_mm.grid;
  for (int k = 0; k < g.dims[2]; k += 7)
    for (int j = 0; j < g.dims[1]; j += 11)
      for (int i = 0; i < g.dims[0]; i += 13) {
        const Eigen::Vector3d x = g.world_mm(i, j, k);
        const Eigen::Vector3d expected = (back * x.homogeneous()).head<3>() - x;
        EXPECT_LT((pc.true_pullback_mm.vectors[g.index(i, j, k)].cast<double>() - expected).norm(), 1e-4);
        // Noise-free T1 is the preop T1 moved rigidly.
        const Eigen::Vector3d p = x + expected;
        EXPECT_NEAR(pc.intraop_t1.at(i, j, k), sample_linear(pre.t1, p, 0.f), 1e-3);
      }
}

TEST(Phantom, ResectionEmptiesTheCavityAndPullsTissueIn) {
  const auto& pre = synthetic_preop();
  PhantomSpec s = small_spec("resection");
  s.sinking.cortex_mm = 6;
  s.resection.enabled = true;
  s.resection.ball_radius_mm = 12;
  s.resection.ball_depth_mm = 20;
  s.resection.collapse_mm = 4;
  s.label_noise_mm = 0;
  const PhantomCase pc = make_phantom(pre.t1, pre.labels, s);
  const PhantomDeformation phi(pre.labels, s);
  const Eigen::Vector3d q = phi.resection_centre_mm();
  // The cavity centre stays fixed under the collapse; find its intraop position.
  const Eigen::Vector3d x = phi.forward(q);
  const Grid3& g = pc.intraop_labels.grid;
  const Eigen::Vector3d v = (g.voxel_from_world() * x.homogeneous()).head<3>();
  EXPECT_EQ(pc.intraop_labels.at(std::lround(v.x()), std::lround(v.y()), std::lround(v.z())), 0);
  // A wall point moves toward the centre by collapse_mm (radially).
  const Eigen::Vector3d wall = q + 12 * Eigen::Vector3d(1, 0, 0);
  const Eigen::Vector3d sunk_q = phi.forward(q), sunk_wall = phi.forward(wall);
  EXPECT_NEAR((sunk_wall - sunk_q).norm(), 12 - 4, 0.6);  // sinking differs slightly across 12 mm
  EXPECT_GT(min_jacobian_determinant(pc.true_pullback_mm), 0.2);
}

TEST(Phantom, RejectsBadSpecs) {
  const auto& pre = synthetic_preop();
  PhantomSpec s = small_spec("bad");
  s.sinking.gravity = Eigen::Vector3d(-0.5, 0.7, 0.5);  // out of the brain
  EXPECT_THROW(make_phantom(pre.t1, pre.labels, s), InputError);
  s = small_spec("bad");
  s.sinking.cortex_mm = 50;
  EXPECT_THROW(make_phantom(pre.t1, pre.labels, s), InputError);
  s = small_spec("bad");
  EXPECT_THROW(make_phantom(pre.t1, LabelImage(pre.labels.grid, 0), s), InputError);
  EXPECT_THROW(make_phantom(ImageF{}, pre.labels, s), InputError);
}

}  // namespace
}  // namespace brainshift

namespace brainshift {
namespace {

TEST(TumorImplant, ALobulatedTumorOfAboutTheAskedSizeInTissueOnly) {
  Preop p = synthetic_preop();
  TumorImplantSpec spec;
  spec.direction = {0.6, 0.5, 0.6};
  spec.depth_mm = 20;
  spec.radius_mm = 10;
  const auto before = p.labels.voxels;
  const TumorImplantResult r = implant_tumor(p.t1, p.labels, spec);
  const double ball_ml = 4.0 / 3.0 * 3.14159265358979 * 1000 / 1000;
  EXPECT_NEAR(r.volume_ml, ball_ml, 0.35 * ball_ml) << "lobulation changes the radius by at most 15 %";
  std::size_t taken = 0, dark = 0;
  for (std::size_t v = 0; v < before.size(); ++v) {
    if (p.labels.voxels[v] != 4) continue;
    ++taken;
    EXPECT_TRUE(before[v] == 1 || before[v] == 3) << "took a voxel of label " << before[v];
    if (p.t1.voxels[v] < 80) ++dark;
  }
  EXPECT_GT(taken, 0u);
  EXPECT_GT(dark, taken * 9 / 10) << "hypointense on the T1";
  // The centre lies depth_mm below the cortex along the direction.
  const Eigen::Vector3d v = (p.labels.grid.voxel_from_world() * r.centre_mm.homogeneous()).head<3>();
  EXPECT_EQ(p.labels.at(std::lround(v.x()), std::lround(v.y()), std::lround(v.z())), 4);
  // A resection phantom on it resects the tumor label (not the default ball).
  PhantomSpec resect;
  resect.sinking.enabled = false;
  resect.resection.enabled = true;
  resect.resection.collapse_mm = 3;
  const PhantomDeformation truth(p.labels, resect);
  EXPECT_TRUE(truth.resection_uses_tumor_label());
  EXPECT_LT((truth.resection_centre_mm() - r.centre_mm).norm(), 2.0);
  // The wall moves in by collapse_mm and moves most: tissue farther out less.
  const Eigen::Vector3d out_dir(1, 0, 0);
  const double R = truth.resection_radius_mm();
  const auto shift = [&](double d) {
    const Eigen::Vector3d q = truth.resection_centre_mm() + d * out_dir;
    return (truth.forward(q) - q).norm();
  };
  EXPECT_NEAR(shift(R), 3.0, 1e-6);
  EXPECT_LT(shift(R + 5), shift(R));
  EXPECT_LT(shift(R + 15), shift(R + 5));
}

TEST(TumorImplant, ACysticTumourHasAFluidCoreAtTheVentriclesT1StillLabelledTumour) {
  Preop p = synthetic_preop();  // ventricles (label 2) at T1 20, tissue about 100
  TumorImplantSpec spec;
  spec.direction = {0.6, 0.5, 0.6};
  spec.depth_mm = 20;
  spec.radius_mm = 10;
  spec.cyst_radius_fraction = 0.6;
  const TumorImplantResult r = implant_tumor(p.t1, p.labels, spec);
  // The core holds about 0.6^3 of the tumour (the walls' rims blur it).
  EXPECT_NEAR(r.cyst_ml / r.volume_ml, 0.216, 0.08);
  const Eigen::Vector3d c = (p.labels.grid.voxel_from_world() * r.centre_mm.homogeneous()).head<3>();
  const int i = std::lround(c.x()), j = std::lround(c.y()), k = std::lround(c.z());
  EXPECT_EQ(p.labels.at(i, j, k), 4) << "the cyst is part of the tumour's label";
  EXPECT_NEAR(p.t1.at(i, j, k), 20.f, 1e-3f) << "the core is at the ventricles' T1";
  // Between the cyst's wall (6 mm, lobulated by at most 15 %) and the
  // tumour's (10 mm): the solid tumour's T1, 0.6 of the brain's median.
  const int ring = std::lround(c.x() + 8.0 / 1.5);
  EXPECT_EQ(p.labels.at(ring, j, k), 4);
  EXPECT_NEAR(p.t1.at(ring, j, k), 60.f, 8.f);
  spec.cyst_radius_fraction = 1.0;
  EXPECT_THROW(implant_tumor(p.t1, p.labels, spec), InputError);
}

TEST(TumorImplant, BadSpecsAreClearErrors) {
  Preop p = synthetic_preop();
  TumorImplantSpec spec;
  spec.radius_mm = 0;
  EXPECT_THROW(implant_tumor(p.t1, p.labels, spec), InputError);
  spec = TumorImplantSpec{};
  spec.depth_mm = 500;  // deeper than the brain
  EXPECT_THROW(implant_tumor(p.t1, p.labels, spec), InputError);
}

}  // namespace
}  // namespace brainshift

namespace brainshift {
namespace {

// The receive array's shading: median 1 about the centre, bright by the
// coils and dark in the middle, scaled by its exponent, and not the
// quadratic the engine's bias model fits (the point of having it).
TEST(PhantomArtefacts, ACoilArrayShadesBrightByTheCoilsDarkInTheMiddleAndIsNoQuadratic) {
  Grid3 g;
  g.dims = {61, 61, 61};
  g.world_from_voxel = Eigen::Matrix4d::Identity();
  g.world_from_voxel.topLeftCorner<3, 3>() *= 3.0;
  g.world_from_voxel.topRightCorner<3, 1>() = Eigen::Vector3d(-90, -90, -90);
  const Eigen::Vector3d centre(0, 0, 0);
  std::mt19937_64 rng(5);
  const auto full = coil_array_bias(g, centre, 8, 120, 45, 60, 1.0, rng);
  rng.seed(5);
  const auto squared = coil_array_bias(g, centre, 8, 120, 45, 60, 2.0, rng);
  rng.seed(5);
  const auto flat = coil_array_bias(g, centre, 8, 120, 45, 60, 0.0, rng);
  std::vector<float> reference;
  float top_edge = 0;
  for (int k = 0; k < 61; ++k)
    for (int j = 0; j < 61; ++j)
      for (int i = 0; i < 61; ++i) {
        const std::size_t v = g.index(i, j, k);
        const Eigen::Vector3d p = g.world_mm(i, j, k);
        if (p.norm() <= 60) reference.push_back(full[v]);
        if (std::abs(p.norm() - 85) < 2 && p.z() > 60) top_edge = std::max(top_edge, full[v]);
        EXPECT_FLOAT_EQ(flat[v], 1.f);
        EXPECT_NEAR(squared[v], full[v] * full[v], 1e-4f * squared[v]);
      }
  std::nth_element(reference.begin(), reference.begin() + reference.size() / 2, reference.end());
  EXPECT_NEAR(reference[reference.size() / 2], 1.0, 0.02);
  const float middle = full[g.index(30, 30, 30)];
  EXPECT_LT(middle, 0.9f) << "the middle of an array is darker than its median";
  EXPECT_GT(top_edge, 1.5f * middle) << "the brain's top, near the coils, is brighter than its middle";
  // The log shading's least-squares quadratic leaves a residual the
  // polynomial bias would not: over the sphere of 85 mm, rms > 0.05.
  Eigen::MatrixXd a;
  std::vector<double> y;
  std::vector<Eigen::Matrix<double, 10, 1>> rows;
  for (int k = 0; k < 61; k += 2)
    for (int j = 0; j < 61; j += 2)
      for (int i = 0; i < 61; i += 2) {
        const Eigen::Vector3d p = g.world_mm(i, j, k) / 85.0;
        if (p.norm() > 1) continue;
        Eigen::Matrix<double, 10, 1> r;
        r << 1, p.x(), p.y(), p.z(), p.x() * p.y(), p.x() * p.z(), p.y() * p.z(), p.x() * p.x(), p.y() * p.y(), p.z() * p.z();
        rows.push_back(r);
        y.push_back(std::log(full[g.index(i, j, k)]));
      }
  a.resize(static_cast<Eigen::Index>(rows.size()), 10);
  Eigen::VectorXd b(static_cast<Eigen::Index>(rows.size()));
  for (std::size_t n = 0; n < rows.size(); ++n) {
    a.row(static_cast<Eigen::Index>(n)) = rows[n].transpose();
    b[static_cast<Eigen::Index>(n)] = y[n];
  }
  const Eigen::VectorXd fit = a.colPivHouseholderQr().solve(b);
  const double rms = std::sqrt((a * fit - b).squaredNorm() / static_cast<double>(rows.size()));
  EXPECT_GT(rms, 0.05) << "the array's shading is close to a quadratic in its log";
}

}  // namespace
}  // namespace brainshift
