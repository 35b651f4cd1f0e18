#pragma once
// `brainshift pull`: a scan's result parts into a folder, as register writes
// them, waiting for the deferred ones; with --scene a 3D Slicer scene of them.
#include <string>
#include <vector>

#include "network_commands.h"

namespace brainshift::cli {

struct PullArgs {
  std::string scan, out;
  std::vector<std::string> parts;
  bool scene = false;
  std::string preop_image, intraop_image;
  std::string format = "nifti";  // "nrrd": also NRRD copies, and the scene uses them
};

int cmd_pull(const NetworkOptions& options, const PullArgs& args);

// The result parts' names on the command line, comma-separated (--parts help).
std::string cli_part_names();

}  // namespace brainshift::cli
