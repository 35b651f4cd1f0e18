#include "server/case_store.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <stdexcept>

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "protocol/timing_log.h"
#include "server/hdf5_file.h"

namespace brainshift::server {
namespace fs = std::filesystem;
using nlohmann::json;

namespace {

constexpr const char* kMetaAttr = "meta";
constexpr const char* kStoreFormat = "brainshift-store-1";

std::vector<hsize_t> zyx_dims(const Grid3& g) {
  return {static_cast<hsize_t>(g.dims[2]), static_cast<hsize_t>(g.dims[1]),
          static_cast<hsize_t>(g.dims[0])};
}

void write_grid(hid_t file, const std::string& name, const Grid3& g) {
  double rows[16];
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) rows[r * 4 + c] = g.world_from_voxel(r, c);
  h5::write_dataset(file, name + "_world_from_voxel", H5T_NATIVE_DOUBLE, {4, 4}, rows);
}

Grid3 read_grid(hid_t file, const std::string& name) {
  const auto dims = h5::dataset_dims(file, name);
  if (dims.size() != 3) throw std::runtime_error("store: " + name + " is not 3-D");
  Grid3 g;
  g.dims = {static_cast<int>(dims[2]), static_cast<int>(dims[1]), static_cast<int>(dims[0])};
  double rows[16];
  h5::read_dataset(file, name + "_world_from_voxel", H5T_NATIVE_DOUBLE, rows);
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) g.world_from_voxel(r, c) = rows[r * 4 + c];
  return g;
}

// Runs a store write; on failure removes what it left (`leftover`, so a full
// disk is not kept full by half a file) and throws StoreWriteError naming the
// system's reason (errno of the failing call: ENOSPC, EFBIG, EROFS, EACCES).
template <class Write>
void guarded_write(const fs::path& leftover, const std::string& what, Write&& write) {
  errno = 0;
  try {
    write();
  } catch (const std::exception& e) {
    const int saved = errno;
    std::error_code ec;
    fs::remove_all(leftover, ec);
    std::string reason = e.what();
    if (saved != 0) reason += std::string(" (") + std::strerror(saved) + ")";
    throw StoreWriteError("cannot write " + what + ": " + reason);
  }
}

// Writes bytes to path and fsyncs it. Throws std::runtime_error (errno set)
// when the system refuses.
void write_and_sync(const fs::path& path, const std::string& bytes) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) throw std::runtime_error("cannot create " + path.string());
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n <= 0) {
      const int saved = errno;
      ::close(fd);
      errno = saved;
      throw std::runtime_error("cannot write " + path.string());
    }
    done += static_cast<std::size_t>(n);
  }
  const bool synced = ::fsync(fd) == 0;
  const int saved = errno;
  // The store is an archive: written once, read back rarely (a pull). Handing
  // its pages back once they are on disk keeps the page cache from growing
  // by ~100 MB per scan, and the next scan's write reuses those pages: on the
  // OR VMs a write into fresh page-cache pages ran at ~300 MB/s (0.34 s for a
  // 93 MB result) against 0.03 s into recycled ones.
  if (synced) ::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED);
  ::close(fd);
  errno = saved;
  if (!synced) throw std::runtime_error("cannot fsync " + path.string());
}

// Writes path via path.tmp + fsync + rename + fsync(dir).
void write_plain_file_atomically(const fs::path& path, const std::string& bytes) {
  const fs::path tmp = path.string() + ".tmp";
  guarded_write(tmp, path.string(), [&] {
    write_and_sync(tmp, bytes);
    fs::rename(tmp, path);
  });
  h5::fsync_path(path.parent_path());
}

// An HDF5 file built in memory by fill (which gets the open file), then
// written like any other file: HDF5 itself never meets a failing disk.
template <class Fill>
std::string hdf5_image(Fill&& fill, std::size_t expected_bytes = 0) {
  std::lock_guard lock(h5::hdf5_mutex());
  h5::Handle file = h5::create_in_memory(expected_bytes);
  fill(file.get());
  return h5::file_image(file.get());
}

template <class Fill>
void write_atomically(const fs::path& path, Fill&& fill, std::size_t expected_bytes = 0) {
  write_plain_file_atomically(path, hdf5_image(fill, expected_bytes));
}

json record_to_json(const ScanRecord& r) {
  json j{{"format", kStoreFormat}, {"scan_id", r.scan_id}, {"sequence", r.sequence},
         {"received_at", r.received_at}, {"digest", r.digest}, {"preop_id", r.preop_id},
         {"has_image", r.has_image}, {"has_labels", r.has_labels}};
  if (r.client_scan_id) j["client_scan_id"] = *r.client_scan_id;
  if (r.labels_use) j["labels_use"] = *r.labels_use;
  return j;
}

std::string hex64(std::uint64_t v) {
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(v));
  return buf;
}

bool is_temporary_name(const std::string& n) {
  return n.rfind(".tmp-", 0) == 0 || (n.size() > 4 && n.compare(n.size() - 4, 4, ".tmp") == 0);
}


}  // namespace

const char* to_string(StoredScanState s) {
  switch (s) {
    case StoredScanState::queued: return "queued";
    case StoredScanState::done: return "done";
    case StoredScanState::failed: return "failed";
  }
  return "?";
}

std::string content_digest(const PushedScan& input) {
  std::uint64_t h = 1469598103934665603ull;
  auto mix = [&h](std::string_view bytes) {
    for (unsigned char c : bytes) {
      h ^= c;
      h *= 1099511628211ull;
    }
  };
  // A scan with labels digests as before image-only scans existed (stored
  // digests stay valid); "no labels" is marked apart from any labels' bytes.
  if (input.labels_bytes) mix(*input.labels_bytes);
  else mix(std::string_view("\x02nolabels", 9));
  // Separates "no image" from "empty image" and the labels/image boundary.
  mix(input.image_bytes ? std::string_view("\x01image") : std::string_view("\x00none", 5));
  if (input.image_bytes) mix(*input.image_bytes);
  // Only when the push said: scans without it digest as before it existed.
  if (input.labels_use) mix("\x03labels_use:" + *input.labels_use);
  return hex64(h) + "-" + std::to_string(input.labels_bytes ? input.labels_bytes->size() : 0) + "-" +
         std::to_string(input.image_bytes ? input.image_bytes->size() : 0);
}

CaseStore::CaseStore(fs::path dir, Mode mode) : dir_(std::move(dir)) {
  if (mode == Mode::read_only) {
    if (!fs::is_directory(dir_ / "scans")) throw std::runtime_error("store " + dir_.string() + ": not a case store");
    load_index();
    return;
  }
  std::error_code ec;
  fs::create_directories(dir_ / "scans", ec);
  if (ec) throw std::runtime_error("store " + dir_.string() + ": cannot create: " + ec.message());
  // Fail now, not at the first scan, when the store is not writable.
  if (::access(dir_.c_str(), W_OK) != 0)
    throw std::runtime_error("store " + dir_.string() + ": not writable");
  remove_leftovers();
  load_index();
}

void CaseStore::remove_leftovers() {
  auto is_tmp = [](const fs::path& p) { return is_temporary_name(p.filename().string()); };
  std::vector<fs::path> doomed;
  for (const auto& e : fs::directory_iterator(dir_))
    if (is_tmp(e.path())) doomed.push_back(e.path());
  for (const auto& e : fs::directory_iterator(dir_ / "scans")) {
    if (is_tmp(e.path())) doomed.push_back(e.path());
    else if (e.is_directory())
      for (const auto& f : fs::directory_iterator(e.path()))
        if (is_tmp(f.path())) doomed.push_back(f.path());
  }
  for (const auto& p : doomed) {
    spdlog::warn("store: removing an unfinished write {}", p.string());
    fs::remove_all(p);
  }
}

std::optional<CaseStore::Entry> CaseStore::read_scan_dir(const fs::path& sdir) const {
  Entry entry;
  std::lock_guard lock(h5::hdf5_mutex());
  try {
    h5::Handle file = h5::open_file_read(sdir / "scan.h5");
    const json meta = json::parse(h5::read_string_attribute(file.get(), kMetaAttr));
    ScanRecord& r = entry.record;
    r.scan_id = meta.at("scan_id").get<std::string>();
    r.sequence = meta.at("sequence").get<std::uint64_t>();
    r.received_at = meta.at("received_at").get<std::string>();
    r.digest = meta.at("digest").get<std::string>();
    r.preop_id = meta.at("preop_id").get<std::string>();
    r.has_image = meta.at("has_image").get<bool>();
    r.has_labels = meta.value("has_labels", true);  // stores written before image-only scans
    if (meta.contains("client_scan_id")) r.client_scan_id = meta["client_scan_id"].get<std::string>();
    if (meta.contains("labels_use")) r.labels_use = meta["labels_use"].get<std::string>();
  } catch (const std::exception& e) {
    spdlog::error("store: ignoring {}: {}", sdir.string(), e.what());
    return std::nullopt;
  }
  const fs::path result = sdir / "result.h5";
  if (!fs::exists(result)) return entry;
  try {
    h5::Handle file = h5::open_file_read(result);
    const json meta = json::parse(h5::read_string_attribute(file.get(), kMetaAttr));
    ScanRecord& r = entry.record;
    r.finished_at = meta.at("finished_at").get<std::string>();
    if (meta.at("state") == "failed") {
      r.state = StoredScanState::failed;
      r.error_code = meta.at("error_code").get<std::string>();
      r.error_message = meta.at("error_message").get<std::string>();
      r.error_stage = meta.at("error_stage").get<std::string>();
    } else {
      r.state = StoredScanState::done;
      const auto kind = protocol::result_kind_from_string(meta.at("kind").get<std::string>());
      if (!kind) throw std::runtime_error("unknown result kind " + meta.at("kind").dump());
      r.result = {*kind, meta.value("fallback_reason", ""), meta.value("caution", "")};
      for (const auto& f : meta.at("files")) {
        const std::string ds = f.at("dataset").get<std::string>();
        entry.files[f.at("name").get<std::string>()] =
            FileRef{h5::dataset_offset(file.get(), ds), f.at("size").get<std::uint64_t>(), ""};
      }
    }
    // Files added later (add_result_file) lie beside result.h5.
    for (const auto& f : fs::directory_iterator(sdir)) {
      const std::string n = f.path().filename().string();
      if (!f.is_regular_file() || n == "scan.h5" || n == "result.h5" || is_temporary_name(n)) continue;
      entry.files[n] = FileRef{0, static_cast<std::uint64_t>(f.file_size()), n};
    }
  } catch (const std::exception& e) {
    // A renamed result.h5 is complete by construction; unreadable means disk
    // damage. The scan is processed again rather than served wrong.
    spdlog::error("store: result of {} unreadable ({}); it will be recomputed", sdir.string(), e.what());
    entry.record.state = StoredScanState::queued;
    entry.files.clear();
  }
  return entry;
}

void CaseStore::load_index() {
  std::lock_guard lock(index_mutex_);
  for (const auto& e : fs::directory_iterator(dir_ / "scans")) {
    if (!e.is_directory() || !fs::exists(e.path() / "scan.h5")) continue;
    auto entry = read_scan_dir(e.path());
    if (!entry) continue;
    const ScanRecord& r = entry->record;
    next_sequence_ = std::max(next_sequence_, r.sequence + 1);
    if (r.client_scan_id) by_client_id_[*r.client_scan_id] = r.scan_id;
    scans_[r.scan_id] = std::move(*entry);
  }
}

fs::path CaseStore::scan_dir(const std::string& scan_id) const { return dir_ / "scans" / scan_id; }

bool CaseStore::has_preop() const { return fs::exists(dir_ / "preop.h5"); }

void CaseStore::save_preop(const PreopRecord& p) {
  if (!p.t1.grid.same_geometry(p.labels.grid))
    throw std::invalid_argument("store: preop t1 and labels must share a grid");
  write_atomically(dir_ / "preop.h5", [&](hid_t f) {
    h5::write_dataset(f, "t1", H5T_NATIVE_FLOAT, zyx_dims(p.t1.grid), p.t1.voxels.data());
    write_grid(f, "t1", p.t1.grid);
    h5::write_dataset(f, "labels", H5T_NATIVE_UINT16, zyx_dims(p.labels.grid), p.labels.voxels.data());
    write_grid(f, "labels", p.labels.grid);
    json meta{{"format", kStoreFormat}, {"preop_id", p.preop_id}, {"source", p.source},
              {"saved_at", protocol::utc_now()}};
    if (p.patient_id) meta["patient_id"] = *p.patient_id;
    h5::write_string_attribute(f, kMetaAttr, meta.dump());
    h5::write_bytes(f, "label_table_json", p.label_table_json);
  });
  // A mesh of another preop must never be used with this one.
  std::error_code ec;
  if (auto stored = load_mesh(p.preop_id); !stored) fs::remove(dir_ / "mesh.h5", ec);
}

PreopRecord CaseStore::load_preop() const {
  PreopRecord p;
  std::lock_guard lock(h5::hdf5_mutex());
  h5::Handle f = h5::open_file_read(dir_ / "preop.h5");
  const json meta = json::parse(h5::read_string_attribute(f.get(), kMetaAttr));
  p.preop_id = meta.at("preop_id").get<std::string>();
  p.source = meta.at("source").get<std::string>();
  if (meta.contains("patient_id")) p.patient_id = meta.at("patient_id").get<std::string>();  // stores before it have none
  p.t1 = ImageF(read_grid(f.get(), "t1"));
  h5::read_dataset(f.get(), "t1", H5T_NATIVE_FLOAT, p.t1.voxels.data());
  p.labels = LabelImage(read_grid(f.get(), "labels"));
  h5::read_dataset(f.get(), "labels", H5T_NATIVE_UINT16, p.labels.voxels.data());
  p.label_table_json = h5::read_bytes(f.get(), "label_table_json");
  return p;
}

void CaseStore::save_mesh(const std::string& preop_id, const TetMesh& m) {
  const hsize_t n = m.nodes_mm.size(), t = m.tets.size(), b = m.boundary_faces.size();
  if (m.tet_labels.size() != t) throw std::invalid_argument("store: tet_labels size != tets");
  std::vector<int> faces(3 * b), neighbours(b);
  for (std::size_t i = 0; i < b; ++i) {
    for (int k = 0; k < 3; ++k) faces[3 * i + k] = m.boundary_faces[i].nodes[k];
    neighbours[i] = m.boundary_faces[i].neighbour_label;
  }
  write_atomically(dir_ / "mesh.h5", [&](hid_t f) {
    // Eigen::Vector3d and std::array<int,4> are packed (static_asserted below).
    h5::write_dataset(f, "nodes_mm", H5T_NATIVE_DOUBLE, {n, 3}, m.nodes_mm.data());
    h5::write_dataset(f, "tets", H5T_NATIVE_INT, {t, 4}, m.tets.data());
    h5::write_dataset(f, "tet_labels", H5T_NATIVE_INT, {t}, m.tet_labels.data());
    h5::write_dataset(f, "boundary_faces", H5T_NATIVE_INT, {b, 3}, faces.data());
    h5::write_dataset(f, "boundary_neighbour_label", H5T_NATIVE_INT, {b}, neighbours.data());
    h5::write_string_attribute(f, kMetaAttr, json{{"format", kStoreFormat}, {"preop_id", preop_id}}.dump());
  });
}
static_assert(sizeof(Eigen::Vector3d) == 3 * sizeof(double));
static_assert(sizeof(std::array<int, 4>) == 4 * sizeof(int));

std::optional<TetMesh> CaseStore::load_mesh(const std::string& preop_id) const {
  const fs::path path = dir_ / "mesh.h5";
  if (!fs::exists(path)) return std::nullopt;
  std::lock_guard lock(h5::hdf5_mutex());
  h5::Handle f = h5::open_file_read(path);
  const json meta = json::parse(h5::read_string_attribute(f.get(), kMetaAttr));
  if (meta.at("preop_id").get<std::string>() != preop_id) return std::nullopt;
  TetMesh m;
  m.nodes_mm.resize(h5::dataset_dims(f.get(), "nodes_mm").at(0));
  h5::read_dataset(f.get(), "nodes_mm", H5T_NATIVE_DOUBLE, m.nodes_mm.data());
  m.tets.resize(h5::dataset_dims(f.get(), "tets").at(0));
  h5::read_dataset(f.get(), "tets", H5T_NATIVE_INT, m.tets.data());
  m.tet_labels.resize(m.tets.size());
  h5::read_dataset(f.get(), "tet_labels", H5T_NATIVE_INT, m.tet_labels.data());
  const std::size_t b = h5::dataset_dims(f.get(), "boundary_faces").at(0);
  std::vector<int> faces(3 * b), neighbours(b);
  h5::read_dataset(f.get(), "boundary_faces", H5T_NATIVE_INT, faces.data());
  h5::read_dataset(f.get(), "boundary_neighbour_label", H5T_NATIVE_INT, neighbours.data());
  m.boundary_faces.resize(b);
  for (std::size_t i = 0; i < b; ++i) {
    m.boundary_faces[i].nodes = {faces[3 * i], faces[3 * i + 1], faces[3 * i + 2]};
    m.boundary_faces[i].neighbour_label = neighbours[i];
  }
  return m;
}

ScanRecord CaseStore::add_scan(const PushedScan& input, const std::optional<std::string>& client_scan_id,
                               const std::string& digest, const std::string& preop_id) {
  ScanRecord r;
  {
    std::lock_guard lock(index_mutex_);
    r.sequence = next_sequence_++;
  }
  char id[32];
  std::snprintf(id, sizeof id, "scan-%06llu", static_cast<unsigned long long>(r.sequence));
  r.scan_id = id;
  r.client_scan_id = client_scan_id;
  r.received_at = protocol::utc_now();
  r.digest = digest;
  r.preop_id = preop_id;
  if (!input.labels_bytes && !input.image_bytes) throw std::invalid_argument("store: a scan needs labels or an image");
  r.has_image = input.image_bytes.has_value();
  r.has_labels = input.labels_bytes.has_value();
  r.labels_use = input.labels_use;

  const std::string image = hdf5_image(
      [&](hid_t f) {
        if (input.labels_bytes) h5::write_bytes(f, "labels", *input.labels_bytes);
        if (input.image_bytes) h5::write_bytes(f, "image", *input.image_bytes);
        h5::write_string_attribute(f, kMetaAttr, record_to_json(r).dump());
      },
      (input.labels_bytes ? input.labels_bytes->size() : 0) + (input.image_bytes ? input.image_bytes->size() : 0));
  const fs::path tmp_dir = dir_ / "scans" / (".tmp-" + r.scan_id);
  guarded_write(tmp_dir, "the pushed scan", [&] {
    fs::create_directories(tmp_dir);
    write_and_sync(tmp_dir / "scan.h5", image);
    h5::fsync_path(tmp_dir);
    fs::rename(tmp_dir, scan_dir(r.scan_id));
  });
  h5::fsync_path(dir_ / "scans");
  std::lock_guard lock(index_mutex_);
  if (r.client_scan_id) by_client_id_[*r.client_scan_id] = r.scan_id;
  scans_[r.scan_id] = Entry{r, {}};
  return r;
}

std::optional<ScanRecord> CaseStore::find(const std::string& scan_id) const {
  std::lock_guard lock(index_mutex_);
  auto it = scans_.find(scan_id);
  if (it == scans_.end()) return std::nullopt;
  return it->second.record;
}

std::optional<ScanRecord> CaseStore::find_by_client_id(const std::string& client_scan_id) const {
  std::lock_guard lock(index_mutex_);
  auto it = by_client_id_.find(client_scan_id);
  if (it == by_client_id_.end()) return std::nullopt;
  return scans_.at(it->second).record;
}

std::vector<ScanRecord> CaseStore::list_newest_first(std::size_t limit) const {
  std::lock_guard lock(index_mutex_);
  std::vector<ScanRecord> out;
  for (const auto& [id, e] : scans_) out.push_back(e.record);
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.sequence > b.sequence; });
  if (out.size() > limit) out.resize(limit);
  return out;
}

std::vector<ScanRecord> CaseStore::queued_oldest_first() const {
  std::lock_guard lock(index_mutex_);
  std::vector<ScanRecord> out;
  for (const auto& [id, e] : scans_)
    if (e.record.state == StoredScanState::queued) out.push_back(e.record);
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.sequence < b.sequence; });
  return out;
}

PushedScan CaseStore::load_scan_input(const std::string& scan_id) const {
  PushedScan in;
  std::lock_guard lock(h5::hdf5_mutex());
  h5::Handle f = h5::open_file_read(scan_dir(scan_id) / "scan.h5");
  if (h5::exists(f.get(), "labels")) in.labels_bytes = h5::read_bytes(f.get(), "labels");
  if (h5::exists(f.get(), "image")) in.image_bytes = h5::read_bytes(f.get(), "image");
  const json meta = json::parse(h5::read_string_attribute(f.get(), kMetaAttr));
  if (meta.contains("labels_use")) in.labels_use = meta["labels_use"].get<std::string>();
  return in;
}

void CaseStore::write_result_file(const std::string& scan_id, const std::string& meta_json,
                                  const std::map<std::string, std::string>& files) {
  std::size_t payload = meta_json.size();
  for (const auto& [name, bytes] : files) payload += bytes.size();
  write_atomically(
      scan_dir(scan_id) / "result.h5",
      [&](hid_t f) {
        h5::write_string_attribute(f, kMetaAttr, meta_json);
        std::size_t i = 0;
        for (const auto& [name, bytes] : files) h5::write_bytes(f, "files/" + std::to_string(i++), bytes);
      },
      payload);
}

void CaseStore::save_result(const std::string& scan_id, const std::map<std::string, std::string>& files,
                            const protocol::ResultKindInfo& result, const std::string& finished_at) {
  if (!find(scan_id)) throw std::invalid_argument("store: unknown scan " + scan_id);
  json meta{{"format", kStoreFormat}, {"state", "done"},
            {"finished_at", finished_at.empty() ? protocol::utc_now() : finished_at},
            {"kind", std::string(protocol::to_string(result.kind))}, {"fallback_reason", result.fallback_reason},
            {"caution", result.caution}, {"files", json::array()}};
  std::size_t i = 0;
  for (const auto& [name, bytes] : files)
    meta["files"].push_back({{"name", name}, {"dataset", "files/" + std::to_string(i++)}, {"size", bytes.size()}});
  write_result_file(scan_id, meta.dump(), files);
  // Offsets come from the renamed file, exactly what read_result_file reads.
  auto entry = read_scan_dir(scan_dir(scan_id));
  if (!entry || entry->record.state != StoredScanState::done)
    throw std::runtime_error("store: the result of " + scan_id + " did not read back");
  std::lock_guard lock(index_mutex_);
  scans_[scan_id] = std::move(*entry);
}

void CaseStore::save_failure(const std::string& scan_id, const std::string& error_code,
                             const std::string& message, const std::string& stage) {
  if (!find(scan_id)) throw std::invalid_argument("store: unknown scan " + scan_id);
  const std::string finished = protocol::utc_now();
  json meta{{"format", kStoreFormat}, {"state", "failed"}, {"finished_at", finished},
            {"error_code", error_code}, {"error_message", message}, {"error_stage", stage}};
  write_result_file(scan_id, meta.dump(), {});
  std::lock_guard lock(index_mutex_);
  ScanRecord& r = scans_.at(scan_id).record;
  r.state = StoredScanState::failed;
  r.finished_at = finished;
  r.error_code = error_code;
  r.error_message = message;
  r.error_stage = stage;
}

void CaseStore::mark_failed_unstored(const std::string& scan_id, const std::string& error_code,
                                     const std::string& message, const std::string& stage) {
  std::lock_guard lock(index_mutex_);
  auto it = scans_.find(scan_id);
  if (it == scans_.end()) return;
  ScanRecord& r = it->second.record;
  r.state = StoredScanState::failed;
  r.finished_at = protocol::utc_now();
  r.error_code = error_code;
  r.error_message = message;
  r.error_stage = stage;
}

void CaseStore::mark_queued(const std::string& scan_id) {
  std::lock_guard lock(index_mutex_);
  auto it = scans_.find(scan_id);
  if (it == scans_.end()) return;
  ScanRecord& r = it->second.record;
  r.state = StoredScanState::queued;
  r.finished_at.reset();
  r.error_code.clear();
  r.error_message.clear();
  r.error_stage.clear();
}

void CaseStore::add_result_file(const std::string& scan_id, const std::string& name, const std::string& bytes) {
  if (name.empty() || name.find('/') != std::string::npos || name == "scan.h5" || name == "result.h5" ||
      name[0] == '.' || is_temporary_name(name))
    throw std::invalid_argument("store: \"" + name + "\" cannot be added as a result file");
  {
    std::lock_guard lock(index_mutex_);
    auto it = scans_.find(scan_id);
    if (it == scans_.end() || it->second.record.state != StoredScanState::done)
      throw std::invalid_argument("store: " + scan_id + " has no result to add " + name + " to");
  }
  write_plain_file_atomically(scan_dir(scan_id) / name, bytes);
  std::lock_guard lock(index_mutex_);
  scans_.at(scan_id).files[name] = FileRef{0, bytes.size(), name};
}

std::vector<std::string> CaseStore::result_file_names(const std::string& scan_id) const {
  std::lock_guard lock(index_mutex_);
  std::vector<std::string> names;
  auto it = scans_.find(scan_id);
  if (it != scans_.end())
    for (const auto& [name, ref] : it->second.files) names.push_back(name);
  return names;
}

std::optional<std::string> CaseStore::read_result_file(const std::string& scan_id,
                                                       const std::string& name) const {
  FileRef ref;
  {
    std::lock_guard lock(index_mutex_);
    auto it = scans_.find(scan_id);
    if (it == scans_.end()) return std::nullopt;
    auto f = it->second.files.find(name);
    if (f == it->second.files.end()) return std::nullopt;
    ref = f->second;
  }
  std::string bytes(ref.size, '\0');
  if (ref.size == 0) return bytes;
  if (ref.offset < 0) throw std::runtime_error("store: " + scan_id + "/" + name + " has no data offset");
  const fs::path path = scan_dir(scan_id) / (ref.file.empty() ? std::string("result.h5") : ref.file);
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw std::runtime_error("store: cannot open " + path.string());
  std::size_t done = 0;
  while (done < ref.size) {
    const ssize_t n = ::pread(fd, bytes.data() + done, ref.size - done, ref.offset + static_cast<off_t>(done));
    if (n <= 0) {
      ::close(fd);
      throw std::runtime_error("store: short read of " + path.string());
    }
    done += static_cast<std::size_t>(n);
  }
  ::close(fd);
  return bytes;
}

}  // namespace brainshift::server
