// The standard phantom suite (brain_shift_phantom.h: standard_phantom_suite):
// named cases that cover the craniotomy sites, patient positions, amplitudes
// and artefacts the registration meets.
#include <string>
#include <vector>

#include "phantom/brain_shift_phantom.h"

namespace brainshift {

std::vector<PhantomSpec> standard_phantom_suite() {
  std::vector<PhantomSpec> suite;
  auto base = [](const std::string& name, std::uint64_t seed) {
    PhantomSpec s;
    s.name = name;
    s.seed = seed;
    return s;
  };
  {  // Supine, frontal craniotomy: the classic case.
    PhantomSpec s = base("left_frontal_sinking_12mm", 11);
    s.sinking.craniotomy_direction = {-0.5, 0.75, 0.45};
    s.sinking.gravity = Eigen::Vector3d(0.3, -0.8, -0.5);
    s.sinking.cortex_mm = 12;
    s.sinking.deep_mm = 2;
    suite.push_back(s);
  }
  {  // Lateral position, large shift after CSF drainage.
    PhantomSpec s = base("right_parietal_sinking_18mm", 12);
    s.sinking.craniotomy_direction = {0.6, -0.5, 0.6};
    s.sinking.gravity = Eigen::Vector3d(-0.8, 0.2, -0.55);
    s.sinking.cortex_mm = 18;
    s.sinking.deep_mm = 3;
    s.sinking.depth_decay_mm = 35;
    s.sinking.lateral_radius_mm = 50;
    suite.push_back(s);
  }
  {  // Prone, small shift, and the head was repositioned.
    PhantomSpec s = base("occipital_sinking_6mm_rigid", 13);
    s.sinking.craniotomy_direction = {0.1, -1.0, 0.2};
    s.sinking.gravity = Eigen::Vector3d(0, 1, 0);
    s.sinking.cortex_mm = 6;
    s.sinking.deep_mm = 1;
    s.rigid.rotation_deg = {3, -2, 4};
    s.rigid.translation_mm = {2, -3, 1.5};
    suite.push_back(s);
  }
  {  // Oedema without an opening, oblique acquisition.
    PhantomSpec s = base("deep_swelling_4mm_oblique", 14);
    s.sinking.enabled = false;
    s.swelling.enabled = true;
    s.swelling.amplitude_mm = 4;
    s.swelling.radius_mm = 25;
    s.swelling.centre_offset_mm = {-25, 10, 15};
    s.rigid.rotation_deg = {-2, 1, 0};
    s.oblique_deg = {12, 0, 8};
    suite.push_back(s);
  }
  {  // A right frontal tumor (12 mm, lobulated) resected under the
     // craniotomy; the cavity collapses.
    PhantomSpec s = base("right_frontal_tumor_resection", 15);
    s.sinking.craniotomy_direction = {0.55, 0.7, 0.45};
    s.sinking.cortex_mm = 8;
    s.sinking.deep_mm = 2;
    TumorImplantSpec tumor;
    tumor.direction = s.sinking.craniotomy_direction;
    tumor.depth_mm = 18;
    tumor.radius_mm = 12;
    tumor.seed = 15;
    s.preop_tumor = tumor;
    s.resection.enabled = true;
    s.resection.collapse_mm = 5;
    suite.push_back(s);
  }
  {  // Lateral decubitus, left temporal; everything at once, noisy, flipped oblique grid.
    PhantomSpec s = base("left_temporal_mixed_noisy", 16);
    s.sinking.craniotomy_direction = {-1.0, 0.1, -0.2};
    s.sinking.gravity = Eigen::Vector3d(1, 0, 0);
    s.sinking.cortex_mm = 15;
    s.sinking.deep_mm = 4;
    s.swelling.enabled = true;
    s.swelling.amplitude_mm = 2;
    s.swelling.centre_offset_mm = {-30, 0, 0};
    s.rigid.rotation_deg = {-4, 3, -2};
    s.rigid.translation_mm = {-3, 2, -2};
    s.oblique_deg = {-10, 6, 0};
    s.flip_first_axis = true;
    s.noise_fraction = 0.06;
    s.bias_amplitude = 0.25;
    s.label_noise_mm = 1.5;
    suite.push_back(s);
  }
  {  // Vertex craniotomy, supine head up: the largest sinking.
    PhantomSpec s = base("vertex_sinking_20mm", 17);
    s.sinking.craniotomy_direction = {0.15, -0.1, 1.0};
    s.sinking.gravity = Eigen::Vector3d(0, 0, -1);
    s.sinking.cortex_mm = 20;
    s.sinking.deep_mm = 5;
    s.sinking.depth_decay_mm = 40;
    s.sinking.lateral_radius_mm = 55;
    suite.push_back(s);
  }
  return suite;
}

}  // namespace brainshift
