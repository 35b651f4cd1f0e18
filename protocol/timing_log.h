#pragma once
// The timing log (PROTOCOL.md, "Timing log"): one JSON object per finished
// stage, written as one line to the log file and carried unchanged in the
// "timing" field of event.stage on the PUB socket. Also the "timings" JSON
// frame of scan.result, which sums up one scan.
#include <chrono>
#include <fstream>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

#include "protocol/common.h"

namespace brainshift::protocol {

enum class StageScope { kPreop, kIntraop };

std::string_view to_string(StageScope scope);
// Stage names the server emits in this version; receivers MUST accept others.
bool is_known_stage(StageScope scope, std::string_view stage);

struct StageTiming {
  StageScope scope = StageScope::kIntraop;
  std::string scan_id{};   // required for intraop stages, empty for preop
  std::string preop_id{};  // required for preop stages, optional for intraop
  std::string stage{};     // [a-z_]{1,32}, e.g. "affine"
  double seconds = 0.0;  // wall-clock duration, >= 0
  std::string t{};         // stage end, ISO-8601 UTC with milliseconds, "...Z"
  bool operator==(const StageTiming&) const = default;
};

// "2024-05-01T12:34:56.789Z".
std::string format_utc(std::chrono::system_clock::time_point when);
std::string utc_now();
bool is_iso8601_utc(std::string_view text);

nlohmann::json to_json_value(const StageTiming& timing);
// Throws ProtocolError(kInvalidRequest) naming the bad field.
StageTiming stage_timing_from_json(const nlohmann::json& j);
// Compact JSON without the trailing newline.
std::string make_stage_log_line(const StageTiming& timing);
StageTiming parse_stage_log_line(std::string_view line);

// Appends one line per stage and flushes it, so a crash loses no finished stage.
class TimingLogFile {
 public:
  explicit TimingLogFile(const std::string& path);  // throws std::runtime_error
  void write(const StageTiming& timing);

 private:
  std::string path_{};
  std::ofstream out_{};
};

// The "timings" frame of scan.result. All durations in seconds.
struct PreopTimings {
  double atlas = 0, mesh = 0, assemble = 0, factorise = 0, total = 0;
  bool operator==(const PreopTimings&) const = default;
};
struct IntraopTimings {
  double read = 0, affine = 0, surface = 0, solve = 0, field = 0, warp = 0, models = 0, total = 0;
  bool operator==(const IntraopTimings&) const = default;
};
struct ScanTimings {
  PreopTimings preop{};
  IntraopTimings intraop{};
  MeshSize mesh{};
  bool operator==(const ScanTimings&) const = default;
};

std::string make_timings_json(const ScanTimings& timings);
ScanTimings parse_timings_json(std::string_view text);

}  // namespace brainshift::protocol
