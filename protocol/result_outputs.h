#pragma once
// The parts of a registration result and every name each goes by: the wire
// (scan.result "parts" and frame names), the CLI (`pull --parts`), the files
// `brainshift register --out` and `pull` write, and the daemon's store; and
// what the daemon does with each: whether it is made after the answer
// (deferred, by which stage), which scans have it, how a crash that lost it
// is repaired. One table; the engine's encoder, the daemon (crash recovery,
// pending parts, unavailable reasons), the OpenIGTLink gateway and the
// client all look parts up here (PROTOCOL.md section 5.4 quotes it). A new
// part is one row (and its enumerator); tests/protocol/test_result_outputs.cpp
// and tests/server/test_result_rows.cpp check every row.
#include <array>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "protocol/stage_names.h"

namespace brainshift::protocol {

enum class ResultPart {
  kDisplacement,     // NIfTI DISPVECT field, RAS+ mm, intraop grid, pull-back
  kDisplacementItk,  // ITK HDF5 DisplacementFieldTransform, LPS mm
  kWarpedImage,      // preop T1 resampled onto the intraop grid
  kWarpedLabels,     // preop labels resampled onto the intraop grid
  kModels,           // one .vtp per structure ("model.<structure>" frames)
  kMetrics,          // JSON
  kTimings,          // JSON, see timing_log.h ScanTimings
  kReport,           // report.png (image/png), rendered after the scan is done
  kUncertainty,      // float32 NIfTI, intraop grid: 95 % band radius (mm) of the answer; after the scan is done
  // Present only when the engine derived them (a scan pushed as an image
  // without labels): the segmentation the registration used, in the label
  // table's values, and the posterior of each voxel's chosen tissue.
  kIntraopLabels,
  kSegmentationConfidence,
};

enum class MediaKind { kNifti, kItkH5, kVtp, kJson, kPng };

// Which scans have a part. A row present for some scans only names what
// decides it; the daemon asks part_expected() with what it knows of the scan
// (ScanFacts), so a new condition is an enumerator and a field there.
enum class PartPresence {
  kEveryScan,
  kWithIntraopImage,  // only when scan.push carried an "image"
  // The engine's segmentation of the image: a scan with an "image" and
  // without "labels", or with labels the push did not ask to use exactly
  // (labels_use, PROTOCOL.md 5.3). Labels whose refinement by the image was
  // refused (or a server configured exact) leave the part out of the result.
  kEngineSegmentation,
};

// What the daemon knows of a scan that decides which parts it has.
struct ScanFacts {
  bool has_image = false;  // scan.push carried an intraop image
  bool has_labels = true;  // scan.push carried intraop labels
  bool labels_exact = false;  // scan.push said labels_use "exact"
};

struct ResultOutput {
  ResultPart part;
  std::string_view wire;   // part and frame name; models: part "models", frames "model.<structure>"
  std::string_view cli;    // `brainshift pull --parts`
  std::string_view file;   // register --out and pull; models: "models/<structure>.vtp"
  // The daemon's store: images plain (the client gzips as it writes the file:
  // gzip of the 47 MB field alone cost the daemon ~1.5 s of latency).
  std::string_view stored;
  MediaKind media;
  // Made off the latency path, after event.scan.done, by the timing-log
  // stage deferred_stage (stage_names.h): a pull finds it "pending" until it
  // is stored. Not deferred: part of the answer, deferred_stage empty.
  bool deferred;
  std::string_view deferred_stage;
  PartPresence presence;
  // A deferred part that re-encodes another stored part is made again from
  // it when a crash lost it (field.h5 from field.nii); any other lost
  // deferred part by registering the stored scan again.
  std::optional<ResultPart> remade_from;
};

// part, wire, cli, file, stored, media, deferred, deferred_stage, presence, remade_from
inline constexpr ResultOutput kResultOutputs[] = {
    {ResultPart::kDisplacement, "displacement", "field", "field.nii.gz", "field.nii", MediaKind::kNifti, false, "",
     PartPresence::kEveryScan, std::nullopt},
    {ResultPart::kDisplacementItk, "displacement_itk", "field_h5", "field.h5", "field.h5", MediaKind::kItkH5, true,
     stages::kItkField, PartPresence::kEveryScan, ResultPart::kDisplacement},
    {ResultPart::kWarpedImage, "warped_image", "warped_image", "warped_image.nii.gz", "warped_image.nii",
     MediaKind::kNifti, false, "", PartPresence::kEveryScan, std::nullopt},
    {ResultPart::kWarpedLabels, "warped_labels", "warped_labels", "warped_labels.nii.gz", "warped_labels.nii",
     MediaKind::kNifti, false, "", PartPresence::kEveryScan, std::nullopt},
    {ResultPart::kModels, "models", "models", "models/<structure>.vtp", "models/<structure>.vtp", MediaKind::kVtp,
     false, "", PartPresence::kEveryScan, std::nullopt},
    {ResultPart::kMetrics, "metrics", "metrics", "metrics.json", "metrics.json", MediaKind::kJson, true, stages::kQualityMetrics,
     PartPresence::kEveryScan, std::nullopt},
    {ResultPart::kTimings, "timings", "timings", "timings.json", "timings.json", MediaKind::kJson, false, "",
     PartPresence::kEveryScan, std::nullopt},
    {ResultPart::kReport, "report", "report", "report.png", "report.png", MediaKind::kPng, true, stages::kReport,
     PartPresence::kWithIntraopImage, std::nullopt},
    {ResultPart::kUncertainty, "uncertainty", "uncertainty", "uncertainty.nii.gz", "uncertainty.nii",
     MediaKind::kNifti, true, stages::kUncertainty, PartPresence::kEveryScan, std::nullopt},
    {ResultPart::kIntraopLabels, "intraop_labels", "intraop_labels", "intraop_labels.nii.gz", "intraop_labels.nii",
     MediaKind::kNifti, false, "", PartPresence::kEngineSegmentation, std::nullopt},
    {ResultPart::kSegmentationConfidence, "segmentation_confidence", "segmentation_confidence",
     "segmentation_confidence.nii.gz", "segmentation_confidence.nii", MediaKind::kNifti, false, "",
     PartPresence::kEngineSegmentation, std::nullopt},
};

const ResultOutput& result_output(ResultPart part);
std::string_view to_string(ResultPart p);  // the wire name
std::optional<ResultPart> result_part_from_string(std::string_view wire);
std::optional<ResultPart> result_part_from_cli(std::string_view cli);

// Whether a scan with these facts has the part (its row's presence).
bool part_expected(ResultPart part, const ScanFacts& scan);
// Why a scan lacks a part it is not expected to have, for scan.result's
// "unavailable" ("no intraop image was pushed"); "" when it is expected.
std::string_view why_not_expected(ResultPart part, const ScanFacts& scan);

// Frame name carrying a single-file part ("displacement", ...); throws
// std::invalid_argument for kModels (one model_frame_name per structure).
std::string frame_name(ResultPart part);
// Names the part may have in the daemon's store, preferred first: the plain
// image ("field.nii"), then register's name ("field.nii.gz"), which stores
// written before images were kept plain hold.
std::vector<std::string> stored_file_names(ResultPart part);

// ---- Structures: names from the daemon's label table ----------------------

// A structure name as the label table gives it: 1..64 of [a-z0-9_], starting
// with a letter. It becomes a frame name and a file name, so nothing else
// (no '/', no '.') may pass.
bool is_valid_structure_name(std::string_view name);
std::string model_frame_name(std::string_view structure);  // "model.brain"
std::string model_file_name(std::string_view structure);   // "models/brain.vtp"
// The structure a model frame or file names; nullopt if it names none.
std::optional<std::string> structure_of_model_frame(std::string_view frame);
std::optional<std::string> structure_of_model_file(std::string_view file);

// register's name for a received frame ("displacement" -> "field.nii.gz",
// "model.brain" -> "models/brain.vtp"); "" for a frame no part has.
std::string file_for_frame(std::string_view frame);
// The part a stored or written file belongs to (either name); nullopt if none.
std::optional<ResultPart> part_of_file(std::string_view file);
// Whether media_type is what a frame of that part carries.
bool media_type_fits(ResultPart part, std::string_view media_type);
// The media type of a frame carrying that file (NIfTI: gzip or plain by the bytes).
std::string result_media_type(std::string_view file, std::string_view bytes);

}  // namespace brainshift::protocol
