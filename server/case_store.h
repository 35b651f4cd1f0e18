#pragma once
// The case store: one directory per case (patient session) holding, in HDF5,
// the preop inputs, the mesh, every received scan and every result.
//
// Layout (every file is written under a temporary name, fsynced, then renamed,
// so a kill -9 at any point leaves either the old state or the new one and the
// store opens without repair; leftovers named *.tmp are deleted on open):
//   <dir>/preop.h5                 t1, labels (+ world_from_voxel), meta JSON
//   <dir>/mesh.h5                  nodes, tets, tet labels, boundary faces
//   <dir>/scans/<scan_id>/scan.h5  the received NIfTI bytes (labels, image: either or both), meta
//   <dir>/scans/<scan_id>/result.h5  output files as byte datasets, or a failure
//   <dir>/scans/<scan_id>/<name>     result files added after the result
//                                    (report.png, rendered off the latency path)
// A scan directory is created as scans/.tmp-<id> and renamed once scan.h5 is
// durable: a scan exists exactly when it was acknowledged. HDF5 files are
// built in memory and written with plain write()/fsync(), so a full disk is
// an ordinary write error (StoreWriteError) that leaves nothing behind.
//
// Thread safety: all methods may be called from any thread. HDF5 calls run
// under h5::hdf5_mutex(); read_result_file() uses pread() at offsets recorded
// in the in-memory index, so serving results never waits for HDF5.
#include <cstdint>
#include <filesystem>
#include <map>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/image.h"
#include "core/tet_mesh.h"
#include "protocol/common.h"
#include "protocol/result_outputs.h"

namespace brainshift::server {

// A write to the store failed (disk full, file-size limit, unwritable or
// vanished directory). Nothing of the failed write is left behind: its
// temporary file is removed, so the store's state is what it was before.
class StoreWriteError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct PreopRecord {
  std::string preop_id;
  std::string source;  // "atlas", "files" or "upload"
  ImageF t1;
  LabelImage labels;
  std::string label_table_json;  // protocol label-table JSON, "" when none was given
  std::optional<std::string> patient_id;  // preop.load's patient_id, when given
};

enum class StoredScanState { queued, done, failed };

struct ScanRecord {
  std::string scan_id;
  std::uint64_t sequence = 0;
  std::optional<std::string> client_scan_id;
  std::string received_at;  // ISO-8601 UTC
  std::string digest;       // of the received bytes, for idempotent pushes
  std::string preop_id;     // the preop the scan was pushed against
  bool has_image = false;
  bool has_labels = true;  // false: an image alone, segmented by the engine
  std::optional<std::string> labels_use;  // scan.push's labels_use, when it said
  StoredScanState state = StoredScanState::queued;
  std::optional<std::string> finished_at;
  // Set when failed: protocol error code name, message and failing stage.
  std::string error_code, error_message, error_stage;
  // Set when done: nonrigid, or the affine-only fallback and why.
  protocol::ResultKindInfo result;
};

// What decides which result parts a stored scan has (result_outputs.h).
inline protocol::ScanFacts scan_facts(const ScanRecord& r) {
  return {r.has_image, r.has_labels, r.labels_use == std::optional<std::string>("exact")};
}

// A scan's bytes exactly as scan.push received them (at least one of the
// two; the engine's decoded form is brainshift::ScanInput).
struct PushedScan {
  std::optional<std::string> labels_bytes;  // NIfTI bytes exactly as received
  std::optional<std::string> image_bytes;   // idem
  std::optional<std::string> labels_use;    // "refine" or "exact" when the push said (PROTOCOL.md 5.3)
};

class CaseStore {
 public:
  enum class Mode {
    owner,     // the daemon: creates the directory, removes temporary leftovers
    read_only  // an export beside a running daemon: touches nothing
  };
  // Loads the index. Throws std::runtime_error when the directory is unusable.
  explicit CaseStore(std::filesystem::path dir, Mode mode = Mode::owner);

  const std::filesystem::path& dir() const { return dir_; }

  // ---- preop ---------------------------------------------------------------
  bool has_preop() const;
  // Replaces the stored preop atomically and drops a mesh of another preop.
  void save_preop(const PreopRecord& preop);
  PreopRecord load_preop() const;  // throws when there is none
  void save_mesh(const std::string& preop_id, const TetMesh& mesh);
  // nullopt when no mesh is stored or it belongs to another preop.
  std::optional<TetMesh> load_mesh(const std::string& preop_id) const;

  // ---- scans ---------------------------------------------------------------
  // Every write below throws StoreWriteError when the store cannot take it.
  // Durably stores a scan and returns its record (new id, state queued).
  ScanRecord add_scan(const PushedScan& input, const std::optional<std::string>& client_scan_id,
                      const std::string& digest, const std::string& preop_id);
  std::optional<ScanRecord> find(const std::string& scan_id) const;
  std::optional<ScanRecord> find_by_client_id(const std::string& client_scan_id) const;
  std::vector<ScanRecord> list_newest_first(std::size_t limit) const;
  std::vector<ScanRecord> queued_oldest_first() const;  // acknowledged, no result
  PushedScan load_scan_input(const std::string& scan_id) const;

  // Stores the result files (name -> bytes, names like "field.nii.gz" or
  // "models/brain.vtp") and marks the scan done, finished at finished_at
  // (ISO-8601 UTC; now when empty).
  void save_result(const std::string& scan_id, const std::map<std::string, std::string>& files,
                   const protocol::ResultKindInfo& result, const std::string& finished_at = "");
  void save_failure(const std::string& scan_id, const std::string& error_code,
                    const std::string& message, const std::string& stage);
  // A result or failure that could not be written: the index shows the scan
  // failed, the store still holds it as acknowledged without a result, so a
  // restart (or mark_queued) processes it again. Never persisted.
  void mark_failed_unstored(const std::string& scan_id, const std::string& error_code,
                            const std::string& message, const std::string& stage);
  // Undoes mark_failed_unstored before the scan is processed again.
  void mark_queued(const std::string& scan_id);
  // Adds one file to a done scan's result (e.g. report.png rendered after the
  // scan was announced) as a plain, fsynced file beside result.h5. name is a
  // plain file name ("report.png"), not one of the store's own files.
  void add_result_file(const std::string& scan_id, const std::string& name, const std::string& bytes);
  std::vector<std::string> result_file_names(const std::string& scan_id) const;
  // nullopt when the scan has no result or no file of that name.
  std::optional<std::string> read_result_file(const std::string& scan_id,
                                              const std::string& name) const;

 private:
  struct FileRef {
    std::int64_t offset = -1;  // -1: empty file
    std::uint64_t size = 0;
    std::string file;          // under the scan directory; "" = result.h5
  };
  struct Entry {
    ScanRecord record;
    std::map<std::string, FileRef> files;
  };

  void remove_leftovers();
  void load_index();
  std::optional<Entry> read_scan_dir(const std::filesystem::path& scan_dir) const;
  void write_result_file(const std::string& scan_id, const std::string& meta_json,
                         const std::map<std::string, std::string>& files);
  std::filesystem::path scan_dir(const std::string& scan_id) const;

  std::filesystem::path dir_;
  mutable std::mutex index_mutex_;
  std::map<std::string, Entry> scans_;                 // by scan_id
  std::map<std::string, std::string> by_client_id_;   // client_scan_id -> scan_id
  std::uint64_t next_sequence_ = 1;
};

// A stable content digest (FNV-1a 64 over the frames, hex): equal bytes give
// equal digests; used only to tell a repeated push from a conflicting one.
std::string content_digest(const PushedScan& input);

const char* to_string(StoredScanState state);

}  // namespace brainshift::server
