#pragma once
// Stored results for the OpenIGTLink gateway tests (test_igtl_gateway,
// test_igtl_queries): done scans in a real case store.
#include <map>
#include <string>

#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "protocol/common.h"
#include "server/case_store.h"
#include "server/server_settings.h"
#include "test_support.h"

namespace brainshift::test {

inline TriSurface triangle_fan(double z) {
  TriSurface s;
  s.vertices_mm = {{0, 0, z}, {10, 0, z}, {0, 10, z}, {-10, 0, z}};
  s.triangles = {{0, 1, 2}, {0, 2, 3}};
  return s;
}

// The result files of a done scan whose field is `value` everywhere, on the
// grid of labels.
inline std::map<std::string, std::string> result_files(const LabelImage& labels, float value) {
  VectorImage3 field(labels.grid);
  for (auto& v : field.vectors) v = Eigen::Vector3f(value, -value, 2 * value);
  std::map<std::string, std::string> files;
  files["field.nii"] = displacement_field_to_bytes(field, false);
  files["warped_image.nii"] = scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, false);
  files["warped_labels.nii.gz"] = label_image_to_bytes(labels, true);
  files["models/brain.vtp"] = vtp_bytes(triangle_fan(value));
  files["models/tumor.vtp"] = vtp_bytes(triangle_fan(-value));
  files["timings.json"] = "{}";
  return files;
}

inline std::string store_done_scan(server::CaseStore& store, const server::PushedScan& input,
                                   const std::map<std::string, std::string>& files,
                                   const protocol::ResultKindInfo& result) {
  const server::ScanRecord rec = store.add_scan(input, std::nullopt, server::content_digest(input), "preop-1");
  store.save_result(rec.scan_id, files, result);
  return rec.scan_id;
}

// Stores a done scan whose field is `value` everywhere, on an n^3 oblique grid.
inline std::string store_result(server::CaseStore& store, float value, int n = 12,
                                protocol::ResultKindInfo result = {}) {
  const LabelImage labels = test::ball_labels(n);
  return store_done_scan(store, {label_image_to_bytes(labels, true), std::nullopt, std::nullopt}, result_files(labels, value), result);
}

// The same for a scan pushed as an image alone: its result also holds the
// engine's segmentation (intraop_labels.nii, the ball's labels) and confidence.
inline std::string store_image_only_result(server::CaseStore& store, float value, int n = 12) {
  const LabelImage labels = test::ball_labels(n);
  std::map<std::string, std::string> files = result_files(labels, value);
  files["intraop_labels.nii"] = label_image_to_bytes(labels, false);
  files["segmentation_confidence.nii"] = scalar_image_to_bytes(ImageF(labels.grid, 0.9f), VoxelType::float32, false);
  return store_done_scan(
      store, {std::nullopt, scalar_image_to_bytes(test::ramp_image(labels.grid), VoxelType::float32, true), std::nullopt},
      files, {});
}

inline server::OpenIgtlinkSettings any_port(std::size_t queue = 32, std::size_t max_clients = 8) {
  server::OpenIgtlinkSettings s;
  s.enabled = true;
  s.port = 0;
  s.queue_messages = queue;
  s.max_clients = max_clients;
  return s;
}

}  // namespace brainshift::test
