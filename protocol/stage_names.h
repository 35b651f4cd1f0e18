#pragma once
// The one vocabulary of stage names (PROTOCOL.md 8.2): what the engine
// reports to its progress callback, what the daemon adds around it, what the
// timing log and event.stage carry and what the timings JSON of a scan is
// keyed by. Header-only and free of any library, so the engine includes it
// (DESIGN.md, "One vocabulary at the seams"). A new stage is a constant here
// and an entry in its list.
#include <array>
#include <string_view>

namespace brainshift::protocol::stages {

// ---- preop (warm-up) ----
inline constexpr std::string_view kAtlas = "atlas";          // reading or building the preop images
inline constexpr std::string_view kMesh = "mesh";
inline constexpr std::string_view kAssemble = "assemble";
inline constexpr std::string_view kFactorise = "factorise";
inline constexpr std::string_view kPreopModels = "models";   // surfaces bound to the mesh, affine samples
// ---- intraop, the engine ----
inline constexpr std::string_view kRead = "read";            // input checks (+ the caller's decoding, in timings)
inline constexpr std::string_view kSegment = "segment";      // automatic segmentation of an image-only scan
inline constexpr std::string_view kAffine = "affine";
inline constexpr std::string_view kSurface = "surface";
inline constexpr std::string_view kSolve = "solve";
inline constexpr std::string_view kField = "field";
inline constexpr std::string_view kRefine = "refine";        // inside "field", reported on its own
inline constexpr std::string_view kWarp = "warp";
inline constexpr std::string_view kModels = "models";
inline constexpr std::string_view kQualityMetrics = "metrics";  // label overlap figures (deferred by the daemon)
// ---- intraop, the daemon around the engine ----
inline constexpr std::string_view kDecode = "decode";        // pushed bytes to images
inline constexpr std::string_view kOutputs = "outputs";      // encoding the result files
inline constexpr std::string_view kStore = "store";          // the durable write, after event.scan.done
inline constexpr std::string_view kItkField = "itk_field";   // deferred field.h5
inline constexpr std::string_view kReport = "report";        // deferred report.png
inline constexpr std::string_view kUncertainty = "uncertainty";  // deferred uncertainty.nii
// ---- both scopes ----
inline constexpr std::string_view kTotal = "total";

// What the timings JSON of a scan holds (PROTOCOL.md 8.3), in its order.
inline constexpr std::array kPreopTimings{kAtlas, kMesh, kAssemble, kFactorise, kTotal};
inline constexpr std::array kIntraopTimings{kRead, kAffine, kSurface, kSolve, kField, kWarp, kModels, kTotal};
// Every name a timing-log line may carry in this version, by scope.
inline constexpr std::array kPreopStages{kAtlas, kMesh, kAssemble, kFactorise, kPreopModels, kTotal};
inline constexpr std::array kIntraopStages{kDecode, kRead, kSegment, kAffine,         kSurface, kSolve,    kField,  kRefine,
                                           kWarp,   kModels, kQualityMetrics, kOutputs, kStore,    kItkField,
                                           kReport, kUncertainty, kTotal};

}  // namespace brainshift::protocol::stages
