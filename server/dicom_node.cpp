#include "server/dicom_node.h"

#include <fcntl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <fstream>
#include <map>
#include <set>

#include <dcmtk/dcmdata/dcdeftag.h>
#include <dcmtk/dcmdata/dcuid.h>
#include <dcmtk/dcmnet/dstorscp.h>
#include <spdlog/spdlog.h>

#include "config/toml_reader.h"
#include "core/errors.h"
#include "core/file_bytes.h"
#include "image/dicom_series.h"

namespace brainshift::server {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

// The largest series read back before queuing: the client's own limit for
// push --dicom (client/format_conversion.cpp), so what passes here passes there.
constexpr std::size_t kMaxSeriesBytes = std::size_t{2} << 30;

// A UID is digits and dots, at most 64 characters (PS3.5 9.1): anything else
// must never become a path component.
bool is_uid(const OFString& uid) {
  if (uid.empty() || uid.size() > 64) return false;
  for (const char c : uid)
    if (!(c == '.' || (c >= '0' && c <= '9'))) return false;
  return uid.front() != '.';
}

// target, or target-2, target-3 ... when a resent series already has a record.
fs::path free_name(const fs::path& target) {
  if (!fs::exists(target)) return target;
  for (int i = 2; i < 10000; ++i) {
    fs::path p = target;
    p += "-" + std::to_string(i);
    if (!fs::exists(p)) return p;
  }
  throw InputError("too many records named " + target.string());
}

// The queue command's exit code and the end of what it printed: a refusal
// (the daemon's reason: another patient, no preop, a full queue) goes into
// the rejected series' reason.txt, so the OR sees why, not only that.
struct CommandOutcome {
  int code = -1;
  std::string output_tail;  // at most kOutputTail characters of stdout and stderr
};
constexpr std::size_t kOutputTail = 2000;

CommandOutcome run_command(std::vector<std::string> argv, const fs::path& series_dir) {
  argv.push_back(series_dir.string());
  std::vector<char*> args;
  for (auto& a : argv) args.push_back(a.data());
  args.push_back(nullptr);
  const std::string log = series_dir.string() + ".log";
  CommandOutcome out;
  const pid_t pid = fork();
  if (pid < 0) return out;
  if (pid == 0) {  // only async-signal-safe calls until exec
    const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
    if (fd >= 0) {
      dup2(fd, STDOUT_FILENO);
      dup2(fd, STDERR_FILENO);
    }
    execvp(args[0], args.data());
    _exit(127);
  }
  int status = 0;
  bool waited = true;
  while (waitpid(pid, &status, 0) < 0)
    if (errno != EINTR) {
      waited = false;
      break;
    }
  if (waited) out.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  // Only the end is read: a command may print without bound.
  std::ifstream in(log, std::ios::binary | std::ios::ate);
  if (in) {
    const std::streamoff size = in.tellg();
    const std::streamoff from = std::max<std::streamoff>(0, size - static_cast<std::streamoff>(kOutputTail));
    out.output_tail.resize(static_cast<std::size_t>(size - from));
    in.seekg(from);
    in.read(out.output_tail.data(), static_cast<std::streamsize>(out.output_tail.size()));
  }
  std::error_code ec;
  fs::remove(log, ec);
  return out;
}

// What the SCP shares with its const notification hook (DCMTK declares
// notifyInstanceStored const).
struct StagingState {
  std::map<std::string, Clock::time_point> pending;  // series UID -> last instance
  std::set<std::string> touched;                     // series of the current association
  bool released = false;
};

class NodeScp : public DcmStorageSCP {
 public:
  NodeScp(const DicomNodeSettings& s, std::function<bool()> stop) : s_(s), stop_(std::move(stop)) {}

 protected:
  OFBool checkCalledAETitleAccepted(const OFString& called) override { return called == s_.ae_title.c_str(); }
  OFBool checkCallingAETitleAccepted(const OFString& calling) override {
    for (const auto& p : s_.allowed_peers)
      if (calling == p.c_str()) return OFTrue;
    spdlog::warn("dicom node: association from unknown AE \"{}\" refused", calling.c_str());
    return OFFalse;
  }

  OFCondition generateDirAndFilename(OFString& filename, OFString& directory, OFString& sop_class,
                                     OFString& sop_instance, DcmDataset* dataset) override {
    OFString series;
    if (!dataset || dataset->findAndGetOFString(DCM_SeriesInstanceUID, series).bad() || !is_uid(series))
      return makeOFCondition(OFM_dcmnet, 1, OF_error, "no valid SeriesInstanceUID");
    if (sop_instance.empty()) dataset->findAndGetOFString(DCM_SOPInstanceUID, sop_instance);
    if (sop_class.empty()) dataset->findAndGetOFString(DCM_SOPClassUID, sop_class);
    if (!is_uid(sop_instance)) return makeOFCondition(OFM_dcmnet, 2, OF_error, "no valid SOPInstanceUID");
    const fs::path dir = s_.staging / series.c_str();
    directory = dir.string().c_str();
    filename = (dir / (std::string(sop_instance.c_str()) + ".dcm")).string().c_str();
    state_.touched.insert(series.c_str());
    return EC_Normal;
  }

  void notifyInstanceStored(const OFString& filename, const OFString&, const OFString&,
                            DcmDataset*) const override {
    const std::string series = fs::path(filename.c_str()).parent_path().filename().string();
    state_.pending[series] = Clock::now();
  }

  void notifyAssociationRequest(const T_ASC_Parameters& params, DcmSCPActionType& action) override {
    state_.released = false;
    state_.touched.clear();
    DcmStorageSCP::notifyAssociationRequest(params, action);
  }
  void notifyReleaseRequest() override {
    state_.released = true;
    DcmStorageSCP::notifyReleaseRequest();
  }
  // An association that ends without a release may have cut a series short:
  // every series it touched is dropped whole (the scanner resends it).
  void notifyAssociationTermination() override {
    if (!state_.released)
      for (const auto& series : state_.touched) {
        spdlog::warn("dicom node: association ended without release: series {} discarded", series);
        std::error_code ec;
        fs::remove_all(s_.staging / series, ec);
        state_.pending.erase(series);
      }
    state_.touched.clear();
    DcmStorageSCP::notifyAssociationTermination();
  }

  OFBool stopAfterConnectionTimeout() override {
    queue_quiet_series();
    return stop_() ? OFTrue : OFFalse;
  }
  OFBool stopAfterCurrentAssociation() override {
    queue_quiet_series();
    return stop_() ? OFTrue : OFFalse;
  }

 private:
  void queue_quiet_series() {
    const auto quiet = std::chrono::duration<double>(s_.series_quiet_s);
    for (auto it = state_.pending.begin(); it != state_.pending.end();) {
      if (Clock::now() - it->second < quiet) {
        ++it;
        continue;
      }
      queue_series(it->first);
      it = state_.pending.erase(it);
    }
  }

  void queue_series(const std::string& series) {
    const fs::path dir = s_.staging / series;
    try {
      read_dicom_series(dir, "", kMaxSeriesBytes);  // refuses missing slices, tilt, ...
    } catch (const std::exception& e) {
      reject(dir, e.what());
      return;
    }
    const fs::path queued = free_name(s_.staging / "queued" / series);
    fs::create_directories(queued.parent_path());
    fs::rename(dir, queued);
    const CommandOutcome rc = run_command(s_.queue_command, queued);
    if (rc.code != 0) {
      reject(queued, "queue command exited with " + std::to_string(rc.code) +
                         (rc.output_tail.empty() ? std::string() : ":\n" + rc.output_tail));
      return;
    }
    spdlog::info("dicom node: series {} queued from {}", series, queued.string());
  }

  void reject(const fs::path& dir, const std::string& why) {
    const fs::path target = free_name(s_.staging / "rejected" / dir.filename());
    spdlog::error("dicom node: series {} not queued: {} (kept in {})", dir.filename().string(), why,
                  target.string());
    fs::create_directories(target.parent_path());
    fs::rename(dir, target);
    std::ofstream(target / "reason.txt") << why << "\n";
  }

  const DicomNodeSettings& s_;
  std::function<bool()> stop_;
  mutable StagingState state_;
};

void accept_storage(NodeScp& scp) {
  // Uncompressed transfer syntaxes only: the series reader uses dcmdata
  // without decoders. (C-ECHO, Verification, is accepted by DcmStorageSCP itself.)
  OFList<OFString> syntaxes;
  syntaxes.push_back(UID_LittleEndianExplicitTransferSyntax);
  syntaxes.push_back(UID_BigEndianExplicitTransferSyntax);
  syntaxes.push_back(UID_LittleEndianImplicitTransferSyntax);
  for (const char* sop : {UID_MRImageStorage, UID_CTImageStorage})
    if (scp.addPresentationContext(sop, syntaxes).bad())
      throw InputError(std::string("dicom node: cannot accept ") + sop);
}

}  // namespace

DicomNodeSettings dicom_node_settings_from_text(const std::string& toml_text, const std::string& source,
                                                const fs::path& base_dir) {
  const toml::table document = config::parse_toml(toml_text, source);
  config::TomlSection root(&document, source, "");
  config::TomlSection t = root.table("dicom_node");
  DicomNodeSettings s;
  t.read("enabled", s.enabled);
  s.ae_title = t.string("ae_title", s.ae_title);
  if (s.ae_title.empty() || s.ae_title.size() > 16) t.fail("ae_title", "1..16 characters (a DICOM AE title)");
  t.read("port", s.port, 1, 65535);
  s.allowed_peers = t.strings("allowed_peers");
  for (const auto& p : s.allowed_peers)
    if (p.empty() || p.size() > 16) t.fail("allowed_peers", "each 1..16 characters (a DICOM AE title)");
  const std::string staging = t.string("staging", "");
  t.read("series_quiet_s", s.series_quiet_s, config::Interval::closed(1.0, 3600.0));
  s.queue_command = t.strings("queue_command");
  t.reject_unknown_keys();
  if (s.enabled) {
    if (s.allowed_peers.empty()) t.fail("allowed_peers", "required when enabled: the scanners' AE titles");
    if (staging.empty()) t.fail("staging", "required when enabled: a directory for incoming series");
    if (s.queue_command.empty()) t.fail("queue_command", "required when enabled, e.g. [\"brainshift\", \"push\", \"--dicom\"]");
  }
  s.staging = fs::path(staging).is_absolute() || staging.empty() ? fs::path(staging) : base_dir / staging;
  return s;
}

DicomNodeSettings dicom_node_settings_from_file(const fs::path& path) {
  return dicom_node_settings_from_text(read_whole_file(path, "configuration file"), path.string(), path.parent_path());
}

// Series folders left by an earlier run (stopped or crashed mid-series) may be
// half-stored, and nothing knows when their last instance came: dropped whole,
// like those of an aborted association.
void discard_leftovers(const fs::path& staging) {
  for (const auto& e : fs::directory_iterator(staging)) {
    const std::string name = e.path().filename().string();
    if (name == "queued" || name == "rejected" || !e.is_directory()) continue;
    spdlog::warn("dicom node: series {} left from an earlier run discarded", name);
    fs::remove_all(e.path());
  }
}

void run_dicom_node(const DicomNodeSettings& s, const std::function<bool()>& stop) {
  fs::create_directories(s.staging);
  discard_leftovers(s.staging);
  NodeScp scp(s, stop);
  scp.setAETitle(s.ae_title.c_str());
  scp.setPort(s.port);
  scp.setOutputDirectory(s.staging.string().c_str());
  scp.setConnectionBlockingMode(DUL_NOBLOCK);
  scp.setConnectionTimeout(1);  // the quiet-series sweep runs about once a second between associations
  scp.setHostLookupEnabled(OFFalse);
  accept_storage(scp);
  spdlog::info("dicom node: {} listening on port {}, peers {}", s.ae_title, s.port, s.allowed_peers.size());
  const OFCondition cond = scp.listen();
  if (cond.bad() && cond != NET_EC_StopAfterConnectionTimeout && cond != NET_EC_StopAfterAssociation)
    throw InputError(std::string("dicom node: ") + cond.text());
}

}  // namespace brainshift::server
