#pragma once
// Broken intraop scans for the bad-input end-to-end test: each is derived from
// a good synthetic scan (scan_a_labels.nii.gz, scan_a_t1.nii.gz in dir) with
// one defect the issue lists.
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace brainshift::e2e {

// One broken scan: the bytes pushed, and a word the error message must contain.
struct ImageCase {
  std::string what;
  std::string labels;
  std::optional<std::string> image;
  std::string fragment;
  bool refused_at_push;  // else stored, then failed by the pipeline
};

std::vector<ImageCase> image_cases(const std::filesystem::path& dir);

// gzip (RFC 1952) of raw bytes, as a .nii.gz file holds them.
std::string gzip(const std::string& raw);

}  // namespace brainshift::e2e
