#include "network_commands.h"

#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <sstream>
#include <thread>

#include <nlohmann/json.hpp>

#include "core/errors.h"
#include "command_support.h"
#include "connection.h"
#include "offline_forwarding.h"
#include "pull_command.h"
#include "protocol/events.h"
#include "protocol/fields.h"
#include "protocol/media.h"
#include "protocol/requests.h"
#include "protocol/result_outputs.h"

namespace brainshift::cli {
using namespace protocol;
using namespace std::chrono_literals;
namespace curve = protocol::curve;

namespace {

Frame nifti_file_frame(const std::string& name, const std::string& path) {
  Frame f = media::nifti_frame(name, read_file(path));
  try {
    media::check_content(f);
  } catch (const ProtocolError& e) {
    throw CommandError(kExitUsage, path + ": " + e.what());
  }
  return f;
}

// A NIfTI file as it is, or a NRRD file converted by brainshift-offline.
Frame input_frame(const NetworkOptions& o, const std::string& name, const std::string& path, bool labels) {
  if (!is_nrrd_name(path)) return nifti_file_frame(name, path);
  if (!o.nrrd_nifti) throw CommandError(kExitUsage, path + ": NRRD needs brainshift-offline (NRRD is read there)");
  try {
    return media::nifti_frame(name, o.nrrd_nifti(path, labels));
  } catch (const InputError& e) {
    throw CommandError(kExitUsage, e.what());
  }
}

template <class Fn>
void run(int* exit_code, Fn&& fn) {
  try {
    *exit_code = fn();
  } catch (const CommandError& e) {
    std::cerr << "brainshift: " << e.what() << '\n';
    *exit_code = e.exit_code();
  } catch (const std::exception& e) {
    std::cerr << "brainshift: " << e.what() << '\n';
    *exit_code = kExitError;
  }
}

std::string describe_event(const Message& e) {
  std::ostringstream os;
  char buf[64];
  switch (e.type()) {
    case MessageType::kEventStage: {
      const StageTiming t = parse_stage_event(e).timing;
      std::snprintf(buf, sizeof buf, "%8.3f s", t.seconds);
      os << "stage    " << (t.scan_id.empty() ? t.preop_id : t.scan_id) << ' ' << t.stage << ' ' << buf;
      break;
    }
    case MessageType::kEventScanProgress: {
      const auto p = parse_scan_progress_event(e);
      os << "progress " << p.scan_id << ' ' << p.stage << ' ' << static_cast<int>(std::lround(p.fraction * 100)) << '%';
      break;
    }
    case MessageType::kEventScanDone: {
      const auto d = parse_scan_done_event(e);
      std::snprintf(buf, sizeof buf, "%.3f s", d.seconds);
      os << "done     " << d.scan_id << ' ' << buf;
      if (d.result) {
        os << ' ' << to_string(d.result->kind);
        if (!d.result->fallback_reason.empty()) os << ": " << d.result->fallback_reason;
        if (!d.result->caution.empty()) os << " CAUTION: " << d.result->caution;
      }
      break;
    }
    case MessageType::kEventScanFailed: {
      const auto f = parse_scan_failed_event(e);
      os << "FAILED   " << f.scan_id << " in " << f.stage << ": " << f.error.message;
      break;
    }
    case MessageType::kEventPreopProgress: {
      const auto p = parse_preop_progress_event(e);
      os << "preop    " << p.preop_id << ' ' << p.stage << ' ' << static_cast<int>(std::lround(p.fraction * 100)) << '%';
      break;
    }
    case MessageType::kEventPreopReady: {
      const auto r = parse_preop_ready_event(e);
      std::snprintf(buf, sizeof buf, "%.2f s", r.seconds);
      os << "ready    " << r.preop_id << ' ' << r.mesh.nodes << " nodes " << r.mesh.tets << " tets " << buf;
      break;
    }
    case MessageType::kEventPreopFailed: {
      const auto f = parse_preop_failed_event(e);
      os << "FAILED   " << f.preop_id << ": " << f.error.message;
      break;
    }
    case MessageType::kEventServerShutdown:
      os << "shutdown " << parse_server_shutdown_event(e).reason;
      break;
    default:
      os << to_string(e.type());
  }
  return os.str();
}

// ---- status ----------------------------------------------------------------

int cmd_status(const NetworkOptions& o, bool json) {
  Connection c(o.server, as_ms(o.timeout_s), curve_keys(o));
  const Message reply = c.call(make_status_request(c.next_request_id()));
  if (json) {
    std::cout << reply.header.dump() << '\n';
    return kExitOk;
  }
  const StatusReply s = parse_status_reply(reply);
  std::cout << "state:   " << to_string(s.state);
  if (s.progress) std::cout << " (" << s.progress->stage << ", " << std::lround(s.progress->fraction * 100) << "%)";
  std::cout << "\npreop:   " << s.preop_id.value_or("-");
  if (s.preop_patient_id) std::cout << " (patient " << *s.preop_patient_id << ')';
  std::cout << '\n';
  if (s.mesh) std::cout << "mesh:    " << s.mesh->nodes << " nodes, " << s.mesh->tets << " tets\n";
  std::cout << "ranks:   " << s.mpi_ranks << "\nqueue:   " << s.queue.depth << " / " << s.queue.capacity << '\n';
  if (s.current_scan_id) std::cout << "running: " << *s.current_scan_id << '\n';
  if (s.openigtlink)
    std::cout << "openigtlink: port " << s.openigtlink->port << ", " << s.openigtlink->clients << " client(s), "
              << s.openigtlink->messages_sent << " message(s) sent, " << s.openigtlink->messages_dropped
              << " dropped\n";
  if (s.last_error) std::cout << "last error: " << to_string(s.last_error->code) << ": " << s.last_error->message << '\n';
  for (const auto& [k, v] : s.versions) std::cout << "version " << k << ": " << v << '\n';
  return kExitOk;
}

// Polls status until the warm-up ends; progress on stderr.
int wait_preop_ready(Connection& c, const std::string& preop_id, double wait_s) {
  const auto deadline = std::chrono::steady_clock::now() + as_ms(wait_s);
  std::string last;
  while (std::chrono::steady_clock::now() < deadline && !interrupted()) {
    const StatusReply s = parse_status_reply(c.call(make_status_request(c.next_request_id())));
    if (s.state == ServerState::kLoadingPreop) {
      std::ostringstream line;
      if (s.progress) line << "warming up: " << s.progress->stage << ' ' << std::lround(s.progress->fraction * 100) << '%';
      if (line.str() != last) std::cerr << (last = line.str()) << '\n';
    } else if (s.preop_id == preop_id && (s.state == ServerState::kReady || s.state == ServerState::kProcessing)) {
      std::cerr << "preop " << preop_id << " ready";
      if (s.mesh) std::cerr << ": " << s.mesh->nodes << " nodes, " << s.mesh->tets << " tets";
      std::cerr << '\n';
      return kExitOk;
    } else {
      throw CommandError(kExitError, "preop " + preop_id + " failed: " +
                                               (s.last_error ? s.last_error->message : std::string("no detail")));
    }
    std::this_thread::sleep_for(250ms);
  }
  throw CommandError(kExitUnreachable, "preop " + preop_id + " not ready within " + std::to_string(wait_s) + " s");
}

// --patient-id as the protocol carries it (usage error when it cannot be one).
std::optional<std::string> patient_id_arg(const std::string& given) {
  if (given.empty()) return std::nullopt;
  std::optional<std::string> id = protocol::detail::normalised_patient_id(given);
  if (!id) throw CommandError(kExitUsage, std::string("--patient-id must be ") + protocol::detail::kPatientIdRule);
  return id;
}

struct LoadPreopArgs {
  std::string image, labels, label_table, patient_id;
  bool default_atlas = false, wait = false;
  double wait_s = 1800;
};

int cmd_load_preop(const NetworkOptions& o, const LoadPreopArgs& a) {
  PreopLoadRequest r;
  r.patient_id = patient_id_arg(a.patient_id);
  if (a.default_atlas) {
    if (!a.image.empty() || !a.labels.empty() || r.patient_id)
      throw CommandError(kExitUsage, "--default-atlas excludes --image/--labels/--patient-id");
    r.use_default_atlas = true;
  } else {
    if (a.image.empty() || a.labels.empty())
      throw CommandError(kExitUsage, "give --image and --labels, or --default-atlas");
    r.t1 = nifti_file_frame("t1", a.image);
    r.labels = nifti_file_frame("labels", a.labels);
    if (!a.label_table.empty()) r.label_table = media::json_frame("label_table", read_file(a.label_table));
  }
  Connection c(o.server, as_ms(std::max(o.timeout_s, 60.0)), curve_keys(o));  // the upload of a 1 mm head takes a moment
  const std::string id = parse_preop_load_reply(c.call(make_preop_load_request(c.next_request_id(), r))).preop_id;
  std::cout << id << '\n' << std::flush;
  return a.wait ? wait_preop_ready(c, id, a.wait_s) : kExitOk;
}

// ---- push ------------------------------------------------------------------

struct PushArgs {
  std::string labels, image, id;
  std::string dicom, series;  // the image as a DICOM series, converted here
  std::string labels_use;     // empty: the daemon's configuration
  std::string patient_id;     // empty: the DICOM series' PatientID, if any
  bool wait = false;
  double wait_s = 600;
};

void announce_result(const ScanResultReply& r) {
  if (const Frame* t = r.find("timings")) {
    try {
      std::cerr << "result ready: intraop " << parse_timings_json(t->bytes).intraop.total << " s\n";
      return;
    } catch (const std::exception&) {
    }
  }
  std::cerr << "result ready\n";
}

bool still_pending(const ScanResultReply& r, std::string_view part) {
  return std::any_of(r.unavailable.begin(), r.unavailable.end(),
                     [&](const UnavailablePart& u) { return u.part == part && u.pending; });
}

int exit_code_of(const ResultKindInfo& result) {
  // A caution does not make the result a fallback: it is non-rigid and
  // usable, to be read with the caution beside it.
  if (!result.caution.empty()) std::cerr << "CAUTION: " << result.caution << '\n';
  if (result.kind == ResultKind::nonrigid) return kExitOk;
  std::cerr << "WARNING: non-rigid registration refused ("
            << (result.fallback_reason.empty() ? "no reason given" : result.fallback_reason)
            << "); the result is the AFFINE-ONLY fallback\n";
  return kExitFallback;
}

// A server before revision 2 of protocol version 1 names the kind only in
// the deferred metrics.json ("result", "fallback_reason"; PROTOCOL.md 10).
int exit_code_of_metrics(const std::string& metrics_json) {
  try {
    const auto metrics = nlohmann::json::parse(metrics_json);
    const auto kind = result_kind_from_string(metrics.value("result", ""));
    if (!kind) throw std::runtime_error("\"result\" is neither nonrigid nor affine_only_fallback");
    return exit_code_of({*kind, metrics.value("fallback_reason", ""), metrics.value("caution", "")});
  } catch (const std::exception& e) {
    throw CommandError(kExitError, std::string("unreadable metrics from the server: ") + e.what());
  }
}

int wait_scan(Connection& c, EventStream& events, const std::string& scan_id, double wait_s) {
  const auto deadline = std::chrono::steady_clock::now() + as_ms(wait_s);
  auto next_poll = std::chrono::steady_clock::now();
  bool announced = false;
  while (std::chrono::steady_clock::now() < deadline && !interrupted()) {
    // Events give live progress and end the wait: this scan's scan.done or
    // scan.failed is followed by a pull at once. The poll every 200 ms only
    // covers an event that was missed (a PUB drops what a slow SUB misses).
    if (auto e = events.next(50ms)) {
      try {
        const std::string text = describe_event(*e);
        if (text.find(scan_id) != std::string::npos) std::cerr << text << '\n';
        if ((e->type() == MessageType::kEventScanDone && parse_scan_done_event(*e).scan_id == scan_id) ||
            (e->type() == MessageType::kEventScanFailed && parse_scan_failed_event(*e).scan_id == scan_id))
          next_poll = std::chrono::steady_clock::now();
      } catch (const std::exception&) {
      }
    }
    if (std::chrono::steady_clock::now() < next_poll) continue;
    next_poll = std::chrono::steady_clock::now() + 200ms;
    const Message reply = c.call_raw(
        make_scan_result_request(c.next_request_id(), {scan_id, {ResultPart::kTimings, ResultPart::kMetrics}, {}}));
    if (reply.type() != MessageType::kError) {
      const auto r = parse_scan_result_reply(reply);
      if (!announced) {
        announced = true;
        announce_result(r);
      }
      // The reply says whether the result is the affine-only fallback, so the
      // wait ends with scan.done; only an older server makes it wait for the
      // deferred metrics, the one place it says so there.
      if (r.result) return exit_code_of(*r.result);
      if (const Frame* m = r.find("metrics")) return exit_code_of_metrics(m->bytes);
      if (still_pending(r, "metrics")) continue;
      std::cerr << "note: " << scan_id << " has no metrics; cannot tell a non-rigid result from the fallback\n";
      return kExitOk;
    }
    const ErrorInfo err = parse_error_reply(reply);
    if (err.code == ErrorCode::kScanFailed) throw CommandError(kExitScanFailed, err.message);
    if (err.code != ErrorCode::kNotReady)
      throw CommandError(kExitError, "server error " + std::string(to_string(err.code)) + ": " + err.message);
  }
  throw CommandError(kExitUnreachable, scan_id + ": no result within " + std::to_string(static_cast<int>(wait_s)) + " s");
}

int cmd_push(const NetworkOptions& o, const PushArgs& a) {
  ScanPushRequest r;
  if (a.labels.empty() && a.image.empty() && a.dicom.empty())
    throw CommandError(kExitUsage, "give --labels, --image (or --dicom), or both: an image alone is segmented");
  if (!a.labels.empty()) r.labels = input_frame(o, "labels", a.labels, true);
  if (!a.image.empty()) r.image = input_frame(o, "image", a.image, false);
  r.patient_id = patient_id_arg(a.patient_id);
  if (!a.dicom.empty()) {
    if (!a.image.empty()) throw CommandError(kExitUsage, "give --image or --dicom, not both");
    if (!o.dicom_nifti) throw CommandError(kExitUsage, "--dicom needs brainshift-offline (DICOM is read there)");
    DicomNifti series;
    try {
      series = o.dicom_nifti(a.dicom, a.series);
    } catch (const InputError& e) {
      throw CommandError(kExitUsage, e.what());
    }
    r.image = media::nifti_frame("image", std::move(series.nifti));
    // The series names its patient: sent, so that the daemon refuses a scan
    // of another patient than the preop's.
    const auto from_series = protocol::detail::normalised_patient_id(series.patient_id);
    if (!from_series && !r.patient_id && series.patient_id.find_first_not_of(' ') != std::string::npos)
      throw CommandError(kExitUsage, "the DICOM series' PatientID is not text brainshift can read (a character set "
                                     "it does not declare, or over 64 bytes): give the patient with --patient-id");
    if (from_series) {
      if (r.patient_id && *r.patient_id != *from_series)
        throw CommandError(kExitUsage, "--patient-id \"" + *r.patient_id + "\" but the DICOM series is of patient \"" +
                                           *from_series + "\"");
      r.patient_id = from_series;
    }
  } else if (!a.series.empty()) {
    throw CommandError(kExitUsage, "--series needs --dicom");
  }
  if (!a.id.empty()) r.client_scan_id = a.id;
  if (!a.labels_use.empty()) {
    if (!r.labels || !r.image) throw CommandError(kExitUsage, "--labels-use needs both --labels and --image");
    r.labels_use = a.labels_use;
  }
  // Subscribed before the push so that no event of this scan is missed.
  std::optional<EventStream> events;
  if (a.wait) events.emplace(o.events, "event.", curve_keys(o));
  Connection c(o.server, as_ms(o.timeout_s), curve_keys(o));
  const ScanPushReply reply = parse_scan_push_reply(c.call(make_scan_push_request(c.next_request_id(), r)));
  std::cout << reply.scan_id << '\n' << std::flush;
  if (reply.duplicate) std::cerr << "note: client scan id already pushed; this is the same scan\n";
  return a.wait ? wait_scan(c, *events, reply.scan_id, a.wait_s) : kExitOk;
}

// ---- list, watch, shutdown -------------------------------------------------

int cmd_list(const NetworkOptions& o, std::uint64_t limit) {
  Connection c(o.server, as_ms(o.timeout_s), curve_keys(o));
  const ScanListReply r = parse_scan_list_reply(c.call(make_scan_list_request(c.next_request_id(), {limit})));
  for (const auto& s : r.scans) {
    std::cout << s.scan_id << '\t' << to_string(s.state) << '\t' << s.received_at << '\t'
              << s.client_scan_id.value_or("-");
    if (s.stage) std::cout << "\tstage " << *s.stage;
    if (s.result) {
      std::cout << '\t' << to_string(s.result->kind);
      if (!s.result->fallback_reason.empty()) std::cout << '\t' << s.result->fallback_reason;
      if (!s.result->caution.empty()) std::cout << "\tCAUTION: " << s.result->caution;
    }
    if (s.error) std::cout << '\t' << s.error->message;
    std::cout << '\n';
  }
  return kExitOk;
}

int cmd_watch(const NetworkOptions& o, bool json, long count, double duration_s) {
  EventStream events(o.events, "", curve_keys(o));
  stop_on_interrupt();
  const auto until = std::chrono::steady_clock::now() + as_ms(duration_s > 0 ? duration_s : 1e9);
  long seen = 0;
  while (!interrupted() && std::chrono::steady_clock::now() < until && (count <= 0 || seen < count)) {
    std::optional<Message> e;
    try {
      e = events.next(200ms);
    } catch (const zmq::error_t& err) {
      if (err.num() == EINTR) continue;  // Ctrl-C: the loop condition ends the watch
      throw;
    } catch (const ProtocolError& err) {
      std::cerr << "brainshift: unreadable event: " << err.what() << '\n';
      continue;
    }
    if (!e) continue;
    ++seen;
    if (json) {
      // Stage events print exactly the timing-log line.
      if (e->type() == MessageType::kEventStage) std::cout << make_stage_log_line(parse_stage_event(*e).timing) << '\n';
      else std::cout << e->header.dump() << '\n';
    } else {
      std::cout << describe_event(*e) << '\n';
    }
    std::cout.flush();
  }
  return kExitOk;
}

int cmd_shutdown(const NetworkOptions& o, const std::string& reason) {
  Connection c(o.server, as_ms(o.timeout_s), curve_keys(o));
  c.call(make_shutdown_request(c.next_request_id(), {reason}));
  std::cerr << "brainshiftd at " << o.server << " is shutting down\n";
  return kExitOk;
}

// ---- keygen ----------------------------------------------------------------

int cmd_keygen(const std::string& prefix) {
  if (!curve::available()) throw CommandError(kExitUsage, "this libzmq has no CURVE support (libsodium)");
  curve::KeyPair pair;
  try {
    pair = curve::write_new_key_pair(prefix);
  } catch (const curve::KeyFileError& e) {
    throw CommandError(kExitUsage, e.what());
  }
  std::cout << pair.public_z85 << '\n';
  std::cerr << "wrote " << curve::secret_key_path(prefix).string() << " (secret, mode 0600: keep it on this machine) and "
            << curve::public_key_path(prefix).string()
            << " (public: put it in the server's allow-list, or give it to clients as --server-key)\n";
  return kExitOk;
}

}  // namespace

CurveKeys curve_keys(const NetworkOptions& o) {
  if (o.key_prefix.empty() && o.server_key_file.empty()) return std::nullopt;
  if (o.key_prefix.empty() || o.server_key_file.empty())
    throw CommandError(kExitUsage, "CURVE needs both --key PREFIX (this client's key pair) and --server-key FILE");
  try {
    return curve::ClientKeys{curve::read_public_key_file(o.server_key_file), curve::read_key_pair(o.key_prefix)};
  } catch (const curve::KeyFileError& e) {
    throw CommandError(kExitUsage, e.what());
  }
}

void add_network_commands(CLI::App& app, NetworkOptions& o, int* exit_code) {
  auto keygen_out = std::make_shared<std::string>();
  auto* keygen = app.add_subcommand("keygen", "make a CURVE key pair: PREFIX.key (public) and PREFIX.key_secret (0600)");
  keygen->add_option("--out", *keygen_out, "file name prefix, e.g. keys/or1-scanner")->required();
  keygen->callback([exit_code, keygen_out] { run(exit_code, [&] { return cmd_keygen(*keygen_out); }); });

  auto* status = app.add_subcommand("status", "server state, preop, mesh size, queue");
  auto json_status = std::make_shared<bool>(false);
  status->add_flag("--json", *json_status, "print the status reply header as JSON");
  status->callback([&o, exit_code, json_status] { run(exit_code, [&] { return cmd_status(o, *json_status); }); });

  auto lp = std::make_shared<LoadPreopArgs>();
  auto* load = app.add_subcommand("load-preop", "send the preop T1 and labels (or choose the default atlas)");
  load->add_option("--image", lp->image, "preop T1 (NIfTI)");
  load->add_option("--labels", lp->labels, "preop label map on the T1's grid (NIfTI)");
  load->add_option("--label-table", lp->label_table, "label table JSON (PROTOCOL.md) when labels are not 1..4");
  load->add_option("--patient-id", lp->patient_id,
                   "the patient the preop is of (DICOM PatientID): the daemon then refuses scans of another patient");
  load->add_flag("--default-atlas", lp->default_atlas, "use the daemon's default atlas (Colin27)");
  load->add_flag("--wait", lp->wait, "return once the warm-up is done (progress on stderr)");
  load->add_option("--wait-timeout", lp->wait_s, "seconds to wait with --wait");
  load->callback([&o, exit_code, lp] { run(exit_code, [&] { return cmd_load_preop(o, *lp); }); });

  auto pa = std::make_shared<PushArgs>();
  auto* push = app.add_subcommand("push", "send an intraop scan; prints its scan id on the first line");
  push->add_option("--labels", pa->labels,
                   "intraop labels (1 brain, 2 ventricles): NIfTI, NRRD or Slicer .seg.nrrd; without them the "
                   "daemon segments the image (pull intraop_labels to see it)");
  push->add_option("--image", pa->image, "intraop T1 (the labels on its grid, or on a part of it, when both are given), NIfTI or NRRD");
  push->add_option("--dicom", pa->dicom, "intraop T1 as a DICOM series folder (sent as NIfTI), instead of --image");
  push->add_option("--series", pa->series, "SeriesInstanceUID in --dicom when the folder holds several");
  push->add_option("--labels-use", pa->labels_use,
                   "labels with an image: refine (the daemon classifies the image under them; an algorithm's "
                   "labels) or exact (used as given; corrected by hand); default: the daemon's given_labels")
      ->check(CLI::IsMember({"refine", "exact"}));
  push->add_option("--id", pa->id, "client scan id: pushing it again returns the same scan");
  push->add_option("--patient-id", pa->patient_id,
                   "the scan's patient (DICOM PatientID; taken from the series with --dicom): refused unless the preop's");
  push->add_flag("--wait", pa->wait,
                 "return once the result is ready (exit 4: affine-only fallback, 5: the scan failed; a caution "
                 "on a non-rigid result is printed, exit 0)");
  push->add_option("--wait-timeout", pa->wait_s, "seconds to wait with --wait");
  push->callback([&o, exit_code, pa] { run(exit_code, [&] { return cmd_push(o, *pa); }); });

  auto pl = std::make_shared<PullArgs>();
  for (const auto& output : kResultOutputs) pl->parts.emplace_back(output.cli);
  auto* pull = app.add_subcommand("pull", "fetch a scan's result into a folder (same names as register --out)");
  pull->add_option("--scan", pl->scan, "scan id")->required();
  pull->add_option("--out", pl->out, "output folder")->required();
  pull->add_option("--parts", pl->parts, cli_part_names())->delimiter(',');
  pull->add_option("--format", pl->format,
                   "nrrd: also write field.nrrd (a 3D Slicer grid transform), warped_image.nrrd and "
                   "warped_labels.nrrd, and the scene uses them")
      ->check(CLI::IsMember({"nifti", "nrrd"}));
  pull->add_flag("--scene", pl->scene,
                 "also write scene.mrml, a 3D Slicer scene of the result (pulls field_h5, warped_image, "
                 "warped_labels and models; named and coloured by the daemon's label table)");
  pull->add_option("--preop-image", pl->preop_image,
                   "preop T1 to copy into the scene, shown under the field (the daemon does not send it)");
  pull->add_option("--intraop-image", pl->intraop_image, "intraop T1 to copy into the scene");
  pull->callback([&o, exit_code, pl] { run(exit_code, [&] { return cmd_pull(o, *pl); }); });

  auto limit = std::make_shared<std::uint64_t>(100);
  auto* list = app.add_subcommand("list", "scans, newest first");
  list->add_option("--limit", *limit, "at most this many (1..1000)");
  list->callback([&o, exit_code, limit] { run(exit_code, [&] { return cmd_list(o, *limit); }); });

  struct WatchArgs {
    bool json = false;
    long count = 0;
    double duration = 0;
  };
  auto wa = std::make_shared<WatchArgs>();
  auto* watch = app.add_subcommand("watch", "live stage timings and events, one line each (Ctrl-C stops)");
  watch->add_flag("--json", wa->json, "one JSON object per line (stage events: the timing-log line)");
  watch->add_option("--count", wa->count, "stop after this many events");
  watch->add_option("--for", wa->duration, "stop after this many seconds");
  watch->callback([&o, exit_code, wa] { run(exit_code, [&] { return cmd_watch(o, wa->json, wa->count, wa->duration); }); });

  auto reason = std::make_shared<std::string>();
  auto* shutdown = app.add_subcommand("shutdown", "stop the daemon cleanly");
  shutdown->add_option("--reason", *reason, "logged by the daemon");
  shutdown->callback([&o, exit_code, reason] { run(exit_code, [&] { return cmd_shutdown(o, *reason); }); });
}

}  // namespace brainshift::cli
