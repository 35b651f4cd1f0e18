#include <algorithm>
#include <cmath>
#include <set>
#include <sstream>

#include "core/errors.h"
#include "pipeline/warm_state.h"

namespace brainshift {
namespace {

std::set<std::uint16_t> present_labels(const LabelImage& labels) {
  std::vector<bool> seen(65536, false);
  for (auto v : labels.voxels) seen[v] = true;
  std::set<std::uint16_t> out;
  for (std::size_t v = 1; v < seen.size(); ++v)
    if (seen[v]) out.insert(static_cast<std::uint16_t>(v));
  return out;
}

void require_known_labels(const LabelImage& labels, const LabelTable& table, const std::string& what) {
  std::ostringstream unknown;
  int count = 0;
  for (auto v : present_labels(labels))
    if (!table.find(v)) unknown << (count++ ? ", " : "") << v;
  if (count)
    throw InputError(what + ": label value(s) " + unknown.str() +
                     " are not in the label table; add them to the table or relabel the image");
}

void require_nonempty_grid(const Grid3& grid, const std::string& what) {
  if (grid.voxel_count() == 0) throw InputError(what + ": the image has no voxels");
}

void require_brain(const LabelImage& labels, std::uint16_t brain, const std::string& what) {
  const bool any = std::any_of(labels.voxels.begin(), labels.voxels.end(),
                               [brain](std::uint16_t v) { return v == brain; });
  if (!any)
    throw InputError(what + ": the brain label (" + std::to_string(brain) + ") is empty");
}

}  // namespace

void validate_preop_input(const PreopInput& input, const LabelTable& table) {
  table.validate();
  require_nonempty_grid(input.labels.grid, "preop labels");
  require_nonempty_grid(input.t1.grid, "preop image");
  if (!input.t1.grid.same_geometry(input.labels.grid))
    throw InputError("preop image and preop labels are on different grids (dimensions or world affine differ)");
  require_known_labels(input.labels, table, "preop labels");
  require_brain(input.labels, table.brain_label(), "preop labels");
}

void validate_intraop_input(const IntraopInput& input, const LabelTable& table) {
  require_nonempty_grid(input.labels.grid, "intraop labels");
  require_known_labels(input.labels, table, "intraop labels");
  require_brain(input.labels, table.brain_label(), "intraop labels");
  if (input.t1) {
    if (!input.t1->grid.same_geometry(input.labels.grid))
      throw InputError("intraop image and intraop labels are on different grids (dimensions or world affine differ)");
  }
}

}  // namespace brainshift
