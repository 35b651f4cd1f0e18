#pragma once
// The intensity refinement's samples: intraop tissue voxels with the preop
// point the FEM's pull-back maps them to, chosen and weighted as
// registration/intensity_refinement.h says. Internal to the refinement.
#include <Eigen/Dense>
#include <cstddef>
#include <vector>

#include "core/image.h"
#include "registration/intensity_lattice.h"
#include "registration/intensity_refinement.h"
#include "registration/linear_sampler.h"

namespace brainshift::intensity {

struct Sample {
  Vec3 base_mm;            // x + u(x): the preop point before the correction
  // d(x + u)/dx at x: how a move of the intraop point moves the preop one.
  Eigen::Matrix3f jac = Eigen::Matrix3f::Identity();
  Eigen::Vector3f poly;    // normalised position, argument of the bias
  Lattice::Cell cell;
  float intensity = 0;     // intraop T1 at x
  float weight = 1;        // boundary down-weighting in [0, 1]
  float bias = 1;          // b(x), current fit
  float score = 0;         // weight * |grad P| when selected
  std::size_t voxel = 0;

  // The preop point once the intraop point has moved by v (the correction is
  // composed with the FEM's pull-back, see apply_correction), to first order.
  Vec3 preop_mm(const Vec3& v) const { return base_mm + jac.cast<double>() * v; }
};

struct Samples {
  std::vector<Sample> motion, bias;
  std::size_t candidates = 0;
  double density_per_mm3 = 0;  // motion samples per mm^3 of usable tissue
};

// Motion samples (the strongest preop gradients) and bias samples (an even
// spread) of the tissue within the lattice's region.
Samples prepare_samples(const VectorImage3& u, const IntensityRefinementInput& in,
                        const IntensityRefinementParameters& p, const Lattice& lattice, const LinearSampler& preop,
                        const Boxes& boxes);

}  // namespace brainshift::intensity
