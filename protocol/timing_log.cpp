#include "protocol/timing_log.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <stdexcept>
#include <tuple>
#include <vector>

#include "protocol/fields.h"
#include "protocol/stage_names.h"
#include "protocol/version.h"

namespace brainshift::protocol {
namespace {

using nlohmann::json;

bool is_stage_name(std::string_view s) {
  if (s.empty() || s.size() > 32) return false;
  for (char c : s)
    if (!((c >= 'a' && c <= 'z') || c == '_')) return false;
  return true;
}

double seconds_field(const detail::FieldReader& f, const char* key) {
  const double s = f.number(key);
  if (s < 0.0) f.fail(key, "must be >= 0 seconds");
  return s;
}

}  // namespace

std::string_view to_string(StageScope scope) {
  return scope == StageScope::kPreop ? "preop" : "intraop";
}

bool is_known_stage(StageScope scope, std::string_view stage) {
  auto in = [&](const auto& names) { return std::find(names.begin(), names.end(), stage) != names.end(); };
  return scope == StageScope::kPreop ? in(stages::kPreopStages) : in(stages::kIntraopStages);
}

std::string format_utc(std::chrono::system_clock::time_point when) {
  using namespace std::chrono;
  const auto ms = duration_cast<milliseconds>(when.time_since_epoch()).count();
  const std::time_t secs = static_cast<std::time_t>(ms >= 0 ? ms / 1000 : (ms - 999) / 1000);
  const int millis = static_cast<int>(ms - static_cast<long long>(secs) * 1000);
  std::tm tm{};
  gmtime_r(&secs, &tm);
  char buf[64];  // room for any int year, which silences -Wformat-truncation
  std::snprintf(buf, sizeof buf, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", tm.tm_year + 1900,
                tm.tm_mon + 1, tm.tm_mday, tm.tm_hour, tm.tm_min, tm.tm_sec, millis);
  return buf;
}

std::string utc_now() { return format_utc(std::chrono::system_clock::now()); }

// YYYY-MM-DDTHH:MM:SS[.f{1,9}]Z, checked by shape (digits and separators).
bool is_iso8601_utc(std::string_view text) {
  constexpr std::string_view shape = "dddd-dd-ddTdd:dd:dd";
  if (text.size() < shape.size() + 1 || text.back() != 'Z') return false;
  for (std::size_t i = 0; i < shape.size(); ++i) {
    const bool ok = shape[i] == 'd' ? (text[i] >= '0' && text[i] <= '9') : text[i] == shape[i];
    if (!ok) return false;
  }
  const std::string_view fraction = text.substr(shape.size(), text.size() - shape.size() - 1);
  if (fraction.empty()) return true;
  if (fraction.size() < 2 || fraction.size() > 10 || fraction[0] != '.') return false;
  for (char c : fraction.substr(1))
    if (c < '0' || c > '9') return false;
  return true;
}

json to_json_value(const StageTiming& t) {
  json j{{"v", kTimingLogVersion}, {"event", "stage"}, {"scope", std::string(to_string(t.scope))}};
  if (!t.scan_id.empty()) j["scan_id"] = t.scan_id;
  if (!t.preop_id.empty()) j["preop_id"] = t.preop_id;
  j["stage"] = t.stage;
  j["seconds"] = t.seconds;
  j["t"] = t.t;
  return j;
}

StageTiming stage_timing_from_json(const json& j) {
  const detail::FieldReader f(j, "timing log line");
  const auto v = f.uint("v");
  if (v != static_cast<std::uint64_t>(kTimingLogVersion))
    f.fail("v", "is " + std::to_string(v) + "; this reader knows timing-log version " +
                    std::to_string(kTimingLogVersion));
  if (f.string("event") != "stage") f.fail("event", "must be \"stage\"");
  StageTiming t;
  const auto scope = f.string("scope");
  if (scope != "preop" && scope != "intraop") f.fail("scope", "must be \"preop\" or \"intraop\"");
  t.scope = scope == "preop" ? StageScope::kPreop : StageScope::kIntraop;
  t.scan_id = f.opt_string("scan_id").value_or("");
  t.preop_id = f.opt_string("preop_id").value_or("");
  if (t.scope == StageScope::kIntraop && t.scan_id.empty())
    f.fail("scan_id", "is required for an intraop stage");
  if (t.scope == StageScope::kPreop && t.preop_id.empty())
    f.fail("preop_id", "is required for a preop stage");
  t.stage = f.string("stage");
  if (!is_stage_name(t.stage)) f.fail("stage", "must match [a-z_]{1,32}");
  t.seconds = seconds_field(f, "seconds");
  t.t = f.string("t");
  if (!is_iso8601_utc(t.t)) f.fail("t", "must be ISO-8601 UTC like 2024-05-01T12:34:56.789Z");
  return t;
}

std::string make_stage_log_line(const StageTiming& timing) {
  // Validate on the way out too: a bad line in the log is found by nobody.
  json j = to_json_value(timing);
  stage_timing_from_json(j);
  return j.dump();
}

StageTiming parse_stage_log_line(std::string_view line) {
  json j = json::parse(line, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded())
    throw ProtocolError(ErrorCode::kMalformedJson, "timing log line is not valid JSON");
  return stage_timing_from_json(j);
}

TimingLogFile::TimingLogFile(const std::string& path) : path_(path), out_(path, std::ios::app) {
  if (!out_) throw std::runtime_error("cannot open timing log " + path + " for appending");
}

void TimingLogFile::write(const StageTiming& timing) {
  out_ << make_stage_log_line(timing) << '\n';
  out_.flush();
  if (!out_) throw std::runtime_error("cannot write to timing log " + path_);
}

namespace {
// The timings' seconds in the order of stages::kPreopTimings / kIntraopTimings.
std::array<double, stages::kPreopTimings.size()> values(const PreopTimings& p) {
  return {p.atlas, p.mesh, p.assemble, p.factorise, p.total};
}
std::array<double, stages::kIntraopTimings.size()> values(const IntraopTimings& i) {
  return {i.read, i.affine, i.surface, i.solve, i.field, i.warp, i.models, i.total};
}
template <class Names, class Values>
json keyed(const Names& names, const Values& seconds) {
  json j = json::object();
  for (std::size_t k = 0; k < names.size(); ++k) j[std::string(names[k])] = seconds[k];
  return j;
}
template <class Names>
std::array<double, std::tuple_size_v<Names>> read_keyed(const detail::FieldReader& f, const Names& names) {
  std::array<double, std::tuple_size_v<Names>> out{};
  for (std::size_t k = 0; k < names.size(); ++k) out[k] = seconds_field(f, std::string(names[k]).c_str());
  return out;
}
}  // namespace

std::string make_timings_json(const ScanTimings& s) {
  json j{{"preop", keyed(stages::kPreopTimings, values(s.preop))},
         {"intraop", keyed(stages::kIntraopTimings, values(s.intraop))},
         {"mesh", to_json_value(s.mesh)}};
  return j.dump(2);
}

ScanTimings parse_timings_json(std::string_view text) {
  json j = json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded())
    throw ProtocolError(ErrorCode::kMalformedJson, "timings frame is not valid JSON");
  const detail::FieldReader top(j, "timings");
  const detail::FieldReader p(top.object("preop"), "timings.preop");
  const detail::FieldReader i(top.object("intraop"), "timings.intraop");
  ScanTimings s;
  const auto pv = read_keyed(p, stages::kPreopTimings);
  s.preop = {pv[0], pv[1], pv[2], pv[3], pv[4]};
  const auto iv = read_keyed(i, stages::kIntraopTimings);
  s.intraop = {iv[0], iv[1], iv[2], iv[3], iv[4], iv[5], iv[6], iv[7]};
  s.mesh = mesh_size_from_json(top.object("mesh"), "timings.mesh");
  return s;
}

}  // namespace brainshift::protocol
