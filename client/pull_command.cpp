#include "pull_command.h"

#include <algorithm>
#include <filesystem>
#include <iostream>
#include <thread>

#include "command_support.h"
#include "connection.h"
#include "pulled_files.h"
#include "slicer_scene.h"
#include "protocol/requests.h"
#include "protocol/result_outputs.h"

namespace brainshift::cli {
namespace fs = std::filesystem;
using namespace protocol;
using namespace std::chrono_literals;

namespace {

// What scene.mrml shows that the daemon sends (the preop and intraop images
// are the user's own files; intraop_labels when the engine segmented the
// image: pushed alone, or labels refined by it).
constexpr ResultPart kScenePartsFromTheDaemon[] = {ResultPart::kDisplacementItk, ResultPart::kWarpedImage,
                                                   ResultPart::kWarpedLabels, ResultPart::kModels,
                                                   ResultPart::kUncertainty, ResultPart::kIntraopLabels};

// Writes the frames as register's files; returns the parts still pending.
std::vector<ResultPart> write_pulled(const ScanResultReply& r, const fs::path& out) {
  for (const Frame& f : r.frames) {
    const PulledFile file = pulled_file_for(f);
    if (file.name.empty()) {
      std::cerr << "note: ignoring unknown frame " << f.name << '\n';
      continue;
    }
    write_file(out / file.name, file.bytes);
    std::cout << (out / file.name).string() << '\n';
  }
  std::vector<ResultPart> pending;
  for (const auto& u : r.unavailable) {
    const auto part = result_part_from_string(u.part);
    if (u.pending && part) pending.push_back(*part);
    else std::cerr << "note: " << u.part << " not available: " << u.reason << '\n';
  }
  return pending;
}

// The daemon's label table, which names and colours the scene (labels.get):
// asked before anything is pulled, so a daemon that cannot say fails first.
std::vector<SceneLabel> daemon_scene_labels(Connection& c) {
  const Message reply = c.call_raw(make_labels_request(c.next_request_id()));
  if (reply.type() == MessageType::kError && parse_error_reply(reply).code == ErrorCode::kUnknownType)
    throw CommandError(kExitError, "pull --scene: this daemon does not serve its label table (labels.get, "
                                   "protocol revision 3; PROTOCOL.md 10); pull without --scene");
  std::vector<SceneLabel> out;
  for (const LabelInfo& l : parse_labels_reply(reply).labels)
    out.push_back({l.value, l.name, l.colour, l.role == kLabelRoleNames[0]});
  return out;
}

// A local image copied into the result folder (the scene refers to it there,
// so the folder stays self-contained): <stem> plus the file's extension.
std::string copy_into(const fs::path& out, const std::string& file, const std::string& stem) {
  if (!fs::is_regular_file(file)) throw CommandError(kExitUsage, file + ": no such file");
  const std::string name = file.size() > 7 && file.compare(file.size() - 7, 7, ".nii.gz") == 0
                               ? stem + ".nii.gz"
                               : stem + fs::path(file).extension().string();
  fs::copy_file(file, out / name, fs::copy_options::overwrite_existing);
  std::cout << (out / name).string() << '\n';
  return name;
}

void write_scene(const PullArgs& a, std::vector<SceneLabel> labels) {
  const fs::path out = a.out;
  SceneContents contents;
  contents.labels = std::move(labels);
  if (!a.preop_image.empty()) contents.preop_image = copy_into(out, a.preop_image, "preop_image");
  if (!a.intraop_image.empty()) contents.intraop_image = copy_into(out, a.intraop_image, "intraop_image");
  contents.nrrd = a.format == "nrrd";
  try {
    write_slicer_scene(out, contents);
  } catch (const std::runtime_error& e) {
    throw CommandError(kExitUsage, e.what());
  }
  std::cout << (out / kSceneFile).string() << '\n';
}

}  // namespace

std::string cli_part_names() {
  std::string out;
  for (const auto& o : kResultOutputs) out += (out.empty() ? "" : ",") + std::string(o.cli);
  return out;
}

int cmd_pull(const NetworkOptions& o, const PullArgs& a) {
  ScanResultRequest req;
  req.scan_id = a.scan;
  std::vector<std::string> parts = a.parts;
  // What the scene shows must be in the folder.
  if (a.scene)
    for (ResultPart p : kScenePartsFromTheDaemon) parts.emplace_back(result_output(p).cli);
  else if (!a.preop_image.empty() || !a.intraop_image.empty())
    throw CommandError(kExitUsage, "--preop-image and --intraop-image go with --scene");
  if (a.scene && a.format == "nrrd") parts.emplace_back(result_output(ResultPart::kDisplacement).cli);
  if (a.format == "nrrd" && !o.nrrd_outputs)
    throw CommandError(kExitUsage, "--format nrrd needs brainshift-offline (NRRD is written there)");
  for (const auto& name : parts) {
    const auto p = result_part_from_cli(name);
    if (!p) throw CommandError(kExitUsage, "unknown part \"" + name + "\"");
    if (std::find(req.parts.begin(), req.parts.end(), *p) == req.parts.end()) req.parts.push_back(*p);
  }
  if (req.parts.empty()) return kExitOk;
  const double timeout_s = std::max(o.timeout_s, 30.0);  // a field is tens of MB
  Connection c(o.server, as_ms(timeout_s), curve_keys(o));
  const std::vector<SceneLabel> labels = a.scene ? daemon_scene_labels(c) : std::vector<SceneLabel>{};
  req.parts = write_pulled(parse_scan_result_reply(c.call(make_scan_result_request(c.next_request_id(), req))), a.out);
  // report.png follows event.scan.done by a moment: ask again for what is
  // pending (only that) until it comes or the timeout ends.
  const auto deadline = std::chrono::steady_clock::now() + as_ms(timeout_s);
  while (!req.parts.empty()) {
    if (std::chrono::steady_clock::now() > deadline || interrupted())
      throw CommandError(kExitUnreachable, a.scan + ": " + std::string(to_string(req.parts.front())) +
                                               " still being produced after " + std::to_string(int(timeout_s)) + " s");
    std::this_thread::sleep_for(200ms);
    req.parts = write_pulled(parse_scan_result_reply(c.call(make_scan_result_request(c.next_request_id(), req))), a.out);
  }
  if (a.format == "nrrd") {
    try {
      o.nrrd_outputs(a.out);
    } catch (const std::exception& e) {
      throw CommandError(kExitError, std::string("writing NRRD: ") + e.what());
    }
  }
  if (a.scene) write_scene(a, labels);
  return kExitOk;
}

}  // namespace brainshift::cli
