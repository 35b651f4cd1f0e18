#pragma once
// The shipped configuration with a coarse mesh (7 mm cells, 4 mm facets):
// the pipeline suites run a whole registration in seconds with it. Header-
// only; its users link brainshift_config.
#include "config_file.h"

namespace brainshift::test {

inline PipelineParameters coarse_parameters() {
  auto p = config::pipeline_parameters_from_text(config::default_config_text(), "built-in");
  p.meshing.cell_size_mm = 7;
  p.meshing.facet_size_mm = 4;
  p.meshing.facet_distance_mm = 1.5;
  return p;
}

}  // namespace brainshift::test
