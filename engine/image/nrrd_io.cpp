#include "image/nrrd_io.h"

#include <algorithm>
#include <bit>
#include <cctype>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <sstream>
#include <vector>

#include "core/errors.h"
#include "core/gzip.h"
#include "core/file_bytes.h"
#include "field/lps.h"
#include "image/nifti_gzip.h"

namespace brainshift {
namespace fs = std::filesystem;
namespace {

// A header is a few KB; a Slicer segmentation with many segments some tens.
constexpr std::size_t kMaxHeaderBytes = 1 << 20;

enum class Scalar { i8, u8, i16, u16, i32, u32, i64, u64, f32, f64 };

struct Nrrd {
  fs::path path;
  Scalar type = Scalar::u8;
  std::size_t bytes_per_value = 1;
  std::vector<long> sizes;
  long layers = 1;  // a leading list axis (a Slicer segmentation's layers), when read
  bool big_endian = false, gzip = false;
  bool lps = true;
  std::vector<Eigen::Vector3d> directions;  // one per spatial axis
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  std::map<std::string, std::string> keys;  // key:=value pairs
  std::string data;                          // the encoded data (after the header, or the data file)
};

std::string trim(std::string s) {
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.back()))) s.pop_back();
  std::size_t i = 0;
  while (i < s.size() && std::isspace(static_cast<unsigned char>(s[i]))) ++i;
  return s.substr(i);
}

[[noreturn]] void fail(const fs::path& p, const std::string& why) { throw InputError("NRRD " + p.string() + ": " + why); }

Scalar scalar_of(const fs::path& p, const std::string& t, std::size_t* bytes) {
  static const std::map<std::string, std::pair<Scalar, std::size_t>> types = {
      {"signed char", {Scalar::i8, 1}}, {"int8", {Scalar::i8, 1}}, {"int8_t", {Scalar::i8, 1}},
      {"uchar", {Scalar::u8, 1}}, {"unsigned char", {Scalar::u8, 1}}, {"uint8", {Scalar::u8, 1}},
      {"uint8_t", {Scalar::u8, 1}}, {"short", {Scalar::i16, 2}}, {"short int", {Scalar::i16, 2}},
      {"signed short", {Scalar::i16, 2}}, {"int16", {Scalar::i16, 2}}, {"int16_t", {Scalar::i16, 2}},
      {"ushort", {Scalar::u16, 2}}, {"unsigned short", {Scalar::u16, 2}}, {"uint16", {Scalar::u16, 2}},
      {"uint16_t", {Scalar::u16, 2}}, {"int", {Scalar::i32, 4}}, {"signed int", {Scalar::i32, 4}},
      {"int32", {Scalar::i32, 4}}, {"int32_t", {Scalar::i32, 4}}, {"uint", {Scalar::u32, 4}},
      {"unsigned int", {Scalar::u32, 4}}, {"uint32", {Scalar::u32, 4}}, {"uint32_t", {Scalar::u32, 4}},
      {"longlong", {Scalar::i64, 8}}, {"long long", {Scalar::i64, 8}}, {"int64", {Scalar::i64, 8}},
      {"int64_t", {Scalar::i64, 8}}, {"ulonglong", {Scalar::u64, 8}}, {"unsigned long long", {Scalar::u64, 8}},
      {"uint64", {Scalar::u64, 8}}, {"uint64_t", {Scalar::u64, 8}}, {"float", {Scalar::f32, 4}},
      {"double", {Scalar::f64, 8}}};
  const auto it = types.find(t);
  if (it == types.end()) fail(p, "type \"" + t + "\" is not read");
  *bytes = it->second.second;
  return it->second.first;
}

// "(1,0,0) (0,1,0) none" -> the vectors; "none" entries left out.
std::vector<Eigen::Vector3d> vectors_of(const fs::path& p, const std::string& text, std::size_t* nones) {
  std::vector<Eigen::Vector3d> out;
  std::istringstream in(text);
  std::string tok;
  *nones = 0;
  while (in >> tok) {
    if (tok == "none") {
      ++*nones;
      continue;
    }
    std::string v = tok;
    while (v.back() != ')' && in >> tok) v += tok;  // "( 1, 0, 0)" spread over tokens
    Eigen::Vector3d d;
    if (std::sscanf(v.c_str(), "(%lf,%lf,%lf)", &d.x(), &d.y(), &d.z()) != 3 || !d.allFinite())
      fail(p, "cannot read the vector \"" + v + "\"");
    out.push_back(d);
  }
  return out;
}

// layered: a leading list axis of several values (the layers of a Slicer
// segmentation whose segments overlap) is kept in Nrrd::layers; otherwise
// only a list axis of one value is read.
Nrrd parse(const fs::path& path, bool layered = false) {
  Nrrd n;
  n.path = path;
  const std::string file = read_whole_file(path, "NRRD file");
  if (file.rfind("NRRD000", 0) != 0) fail(path, "not a NRRD file (no NRRD000x magic)");
  std::size_t at = file.find('\n');
  std::string data_file;
  bool ended = false, space_seen = false;
  std::size_t nones = 0;
  bool list_axis_first = false;
  while (at != std::string::npos && at + 1 <= file.size()) {
    if (at > kMaxHeaderBytes) fail(path, "header longer than 1 MB");
    const std::size_t next = file.find('\n', at + 1);
    std::string line = file.substr(at + 1, (next == std::string::npos ? file.size() : next) - at - 1);
    at = next;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty()) {
      ended = true;
      break;
    }
    if (line[0] == '#') continue;
    if (const auto kv = line.find(":="); kv != std::string::npos) {
      n.keys[line.substr(0, kv)] = line.substr(kv + 2);
      continue;
    }
    const auto colon = line.find(": ");
    if (colon == std::string::npos) fail(path, "header line \"" + line + "\" is neither a field nor a key");
    const std::string field = line.substr(0, colon), value = trim(line.substr(colon + 2));
    if (field == "type") n.type = scalar_of(path, value, &n.bytes_per_value);
    else if (field == "dimension") n.sizes.resize(static_cast<std::size_t>(std::stoul(value)));
    else if (field == "sizes") {
      std::istringstream in(value);
      n.sizes.clear();
      for (long s; in >> s;) n.sizes.push_back(s);
    } else if (field == "endian") n.big_endian = value == "big";
    else if (field == "encoding") {
      if (value == "gzip" || value == "gz") n.gzip = true;
      else if (value != "raw") fail(path, "encoding \"" + value + "\" is not read (raw, gzip)");
    } else if (field == "space") {
      space_seen = true;
      if (value == "left-posterior-superior" || value == "LPS") n.lps = true;
      else if (value == "right-anterior-superior" || value == "RAS") n.lps = false;
      else fail(path, "space \"" + value + "\": only left-posterior-superior and right-anterior-superior are read");
    } else if (field == "space directions") {
      n.directions = vectors_of(path, value, &nones);
      list_axis_first = value.rfind("none", 0) == 0;
    }
    else if (field == "space origin") {
      std::size_t none = 0;
      const auto o = vectors_of(path, value, &none);
      if (o.size() != 1) fail(path, "space origin \"" + value + "\"");
      n.origin = o[0];
    } else if (field == "data file" || field == "datafile") data_file = value;
    else if ((field == "byte skip" || field == "line skip") && value != "0") fail(path, field + " is not read");
    else if (field == "space units" && value.find("mm") == std::string::npos) fail(path, "space units are not mm");
    // kinds, centerings, space dimension, content, measurement frame...: not needed.
  }
  if (!ended && data_file.empty()) fail(path, "no blank line after the header");
  if (!space_seen) fail(path, "no space field (left-posterior-superior or right-anterior-superior): the frame is unknown");
  if (n.directions.size() != 3) fail(path, "needs space directions for 3 spatial axes");
  if (n.sizes.size() != 3 + nones) fail(path, "sizes do not match the space directions");
  if (nones > 0 && !(nones == 1 && !n.directions.empty())) fail(path, "more than one non-spatial axis");
  constexpr long kMaxLayers = 64;
  if (nones == 1 && n.sizes.front() != 1 && !(layered && list_axis_first && n.sizes.front() <= kMaxLayers))
    fail(path, "a non-spatial axis of " + std::to_string(n.sizes.front()) + " values (" +
                   (layered ? "more than 64 layers, or not the first axis" : "several layers or components") +
                   ") is not read");
  if (nones == 1) {
    n.layers = n.sizes.front();
    n.sizes.erase(n.sizes.begin());
  }
  for (long s : n.sizes)
    if (s < 1 || s > (1L << 20)) fail(path, "size " + std::to_string(s) + " out of range");
  if (data_file.empty()) n.data = file.substr(at == std::string::npos ? file.size() : at + 1);
  else if (data_file.rfind("LIST", 0) == 0 || data_file.find('%') != std::string::npos)
    fail(path, "multi-file data (\"" + data_file + "\") is not read");
  else n.data = read_whole_file(path.parent_path() / data_file, "NRRD data file");
  return n;
}

Grid3 grid_of(const Nrrd& n) {
  Grid3 g;
  for (int a = 0; a < 3; ++a) g.dims[a] = static_cast<int>(n.sizes[static_cast<std::size_t>(a)]);
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  for (int a = 0; a < 3; ++a) m.block<3, 1>(0, a) = n.directions[static_cast<std::size_t>(a)];
  m.block<3, 1>(0, 3) = n.origin;
  if (std::abs(m.topLeftCorner<3, 3>().determinant()) < 1e-12) fail(n.path, "space directions are degenerate");
  g.world_from_voxel = n.lps ? ras_world_from_lps_world_matrix(m) : m;
  return g;
}

template <class T>
double value_at(const char* p, bool swap) {
  T v;
  std::memcpy(&v, p, sizeof v);
  if (swap) {
    auto* b = reinterpret_cast<unsigned char*>(&v);
    std::reverse(b, b + sizeof v);
  }
  return static_cast<double>(v);
}

// The values, decoded to double one at a time into emit(index, value): a
// voxel's layers (Nrrd::layers) side by side, voxel after voxel.
template <class Emit>
Grid3 decode(const Nrrd& n, std::size_t max_bytes, std::size_t out_bytes_per_voxel, Emit emit) {
  const Grid3 g = grid_of(n);
  const std::size_t count = g.voxel_count() * static_cast<std::size_t>(n.layers);
  if (count * out_bytes_per_voxel > max_bytes || count * n.bytes_per_value > max_bytes)
    fail(n.path, std::to_string(count) + " voxels exceed the " + std::to_string(max_bytes) + " bytes allowed");
  std::string raw(count * n.bytes_per_value, '\0');
  nifti_detail::ByteStream stream(n.data, n.path.string());
  if (stream.read(raw.data(), raw.size()) != raw.size()) fail(n.path, "data shorter than the sizes say");
  const bool swap = n.big_endian != (std::endian::native == std::endian::big);
  for (std::size_t i = 0; i < count; ++i) {
    const char* p = raw.data() + i * n.bytes_per_value;
    double v = 0;
    switch (n.type) {
      case Scalar::i8: v = value_at<std::int8_t>(p, false); break;
      case Scalar::u8: v = value_at<std::uint8_t>(p, false); break;
      case Scalar::i16: v = value_at<std::int16_t>(p, swap); break;
      case Scalar::u16: v = value_at<std::uint16_t>(p, swap); break;
      case Scalar::i32: v = value_at<std::int32_t>(p, swap); break;
      case Scalar::u32: v = value_at<std::uint32_t>(p, swap); break;
      case Scalar::i64: v = value_at<std::int64_t>(p, swap); break;
      case Scalar::u64: v = value_at<std::uint64_t>(p, swap); break;
      case Scalar::f32: v = value_at<float>(p, swap); break;
      case Scalar::f64: v = value_at<double>(p, swap); break;
    }
    if (!std::isfinite(v)) fail(n.path, "a voxel is NaN or infinite");
    emit(i, v);
  }
  return g;
}

LabelImage labels_of(const Nrrd& n, std::size_t max_bytes) {
  LabelImage out;
  std::vector<std::uint16_t> voxels;
  out.grid = decode(n, max_bytes, 2, [&](std::size_t i, double v) {
    if (v < 0 || v > 65535 || v != std::floor(v)) fail(n.path, "label value " + std::to_string(v) + " is not in 0..65535");
    if (voxels.empty()) voxels.resize(grid_of(n).voxel_count());
    voxels[i] = static_cast<std::uint16_t>(v);
  });
  out.voxels = std::move(voxels);
  return out;
}

std::string lower(std::string s) {
  for (auto& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

std::string vec(const Eigen::Vector3d& v) {
  std::ostringstream os;
  os.precision(17);
  os << '(' << v.x() << ',' << v.y() << ',' << v.z() << ')';
  return os.str();
}

// Header of a written file: LPS, gzip, little endian.
std::string header(const Grid3& grid, const char* type, bool vector) {
  const Eigen::Matrix4d lps = lps_world_from_ras_world_matrix(grid.world_from_voxel);
  std::ostringstream h;
  h << "NRRD0004\n# written by brainshift\ntype: " << type << "\ndimension: " << (vector ? 4 : 3)
    << "\nspace: left-posterior-superior\nsizes: " << (vector ? "3 " : "") << grid.dims[0] << ' ' << grid.dims[1]
    << ' ' << grid.dims[2] << "\nspace directions: " << (vector ? "none " : "") << vec(lps.block<3, 1>(0, 0)) << ' '
    << vec(lps.block<3, 1>(0, 1)) << ' ' << vec(lps.block<3, 1>(0, 2)) << "\nkinds: " << (vector ? "vector " : "")
    << "domain domain domain\nendian: little\nencoding: gzip\nspace origin: " << vec(lps.block<3, 1>(0, 3)) << '\n';
  return h.str();
}

void write(const fs::path& path, const std::string& head, const std::string& raw) {
  static_assert(std::endian::native == std::endian::little, "NRRD is written little endian");
  if (path.has_parent_path()) fs::create_directories(path.parent_path());
  std::ofstream out(path, std::ios::binary);
  out << head << '\n' << gzip_bytes(raw);
  if (!out) throw std::runtime_error("cannot write " + path.string());
}

}  // namespace

bool is_nrrd_path(const fs::path& path) {
  const std::string e = lower(path.extension().string());
  return e == ".nrrd" || e == ".nhdr";
}

bool is_slicer_segmentation_path(const fs::path& path) {
  const std::string name = lower(path.filename().string());
  return name.size() > 9 && name.compare(name.size() - 9, 9, ".seg.nrrd") == 0;
}

ImageF read_nrrd_scalar(const fs::path& path, std::size_t max_bytes) {
  const Nrrd n = parse(path);
  ImageF out;
  std::vector<float> voxels;
  out.grid = decode(n, max_bytes, 4, [&](std::size_t i, double v) {
    if (voxels.empty()) voxels.resize(grid_of(n).voxel_count());
    voxels[i] = static_cast<float>(v);
  });
  out.voxels = std::move(voxels);
  return out;
}

LabelImage read_nrrd_labels(const fs::path& path, std::size_t max_bytes) { return labels_of(parse(path), max_bytes); }

namespace {

// A segment of a Slicer segmentation: where it is stored (layer, value) and
// the label table's entry its name matches.
struct Segment {
  std::string name;
  long layer = 0;
  std::uint16_t stored = 0;
  std::uint16_t table_value = 0;
};

// A segment's name as the table spells names: lower case, a space or a
// hyphen as "_" ("Corticospinal tract" is corticospinal_tract).
std::string as_table_name(const std::string& segment_name) {
  std::string s = lower(trim(segment_name));
  for (char& c : s)
    if (c == ' ' || c == '-') c = '_';
  return s;
}

std::vector<Segment> segments_of(const Nrrd& n, const LabelTable& table) {
  std::vector<Segment> out;
  for (int s = 0; s < 1000; ++s) {
    const std::string k = "Segment" + std::to_string(s) + "_";
    const auto name = n.keys.find(k + "Name");
    if (name == n.keys.end()) break;
    const auto value = n.keys.find(k + "LabelValue");
    const auto layer = n.keys.find(k + "Layer");
    if (value == n.keys.end()) fail(n.path, k + "LabelValue missing");
    Segment seg;
    seg.name = trim(name->second);
    try {
      seg.layer = layer == n.keys.end() ? 0 : std::stol(layer->second);
      const unsigned long v = std::stoul(value->second);
      if (v == 0 || v > 65535) throw std::out_of_range("label value");
      seg.stored = static_cast<std::uint16_t>(v);
    } catch (const std::logic_error&) {
      fail(n.path, k + "Layer or " + k + "LabelValue is not a number in range");
    }
    if (seg.layer < 0 || seg.layer >= n.layers)
      fail(n.path, k + "Layer " + std::to_string(seg.layer) + " is not one of the file's " + std::to_string(n.layers) + " layers");
    const LabelEntry* entry = nullptr;
    for (const auto& e : table.entries)
      if (lower(e.name) == as_table_name(seg.name) || lower(short_name_of(e)) == as_table_name(seg.name)) entry = &e;
    if (!entry) {
      std::string names;
      for (const auto& e : table.entries) names += (names.empty() ? "" : ", ") + e.name;
      fail(n.path, "segment \"" + name->second + "\" is not in the label table (" + names + ")");
    }
    seg.table_value = entry->value;
    out.push_back(seg);
  }
  if (out.empty()) fail(n.path, "no Segment0_Name: not a Slicer segmentation");
  return out;
}

}  // namespace

LabelImage read_slicer_segmentation(const fs::path& path, const LabelTable& table, std::size_t max_bytes) {
  const Nrrd n = parse(path, true);
  const std::vector<Segment> segments = segments_of(n, table);
  // (layer, stored value) -> the segment stored so.
  std::map<std::pair<long, std::uint16_t>, std::size_t> stored_as;
  for (std::size_t s = 0; s < segments.size(); ++s)
    if (!stored_as.emplace(std::make_pair(segments[s].layer, segments[s].stored), s).second)
      fail(path, "two segments are stored as value " + std::to_string(segments[s].stored) + " in layer " +
                     std::to_string(segments[s].layer));
  // The container: the table's parenchyma label (none in a table without one).
  std::uint16_t brain = 0;
  for (const auto& e : table.entries)
    if (e.role == LabelRole::parenchyma) brain = e.value;
  const auto L = static_cast<std::size_t>(n.layers);
  LabelImage out;
  std::vector<std::uint16_t>& voxels = out.voxels;
  // Segments may overlap only across layers. The brain is the container of
  // the others (ventricles, tract, tumour lie in it): where it overlaps one,
  // the other is kept. Two other structures overlapping (a tumour over the
  // tract) are the site's to resolve: which one a voxel is decides its
  // material and whether it is resected.
  std::size_t overlaps = 0;
  std::pair<std::size_t, std::size_t> first_overlap{0, 0};
  std::vector<std::size_t> in_voxel(segments.size(), 0);
  out.grid = decode(n, max_bytes, 2, [&](std::size_t i, double v) {
    if (v < 0 || v > 65535 || v != std::floor(v)) fail(path, "label value " + std::to_string(v) + " is not in 0..65535");
    if (voxels.empty()) voxels.resize(grid_of(n).voxel_count(), 0);
    if (v == 0) return;
    const std::size_t voxel = i / L;
    const long layer = static_cast<long>(i % L);
    const auto it = stored_as.find({layer, static_cast<std::uint16_t>(v)});
    if (it == stored_as.end())
      fail(path, "voxel value " + std::to_string(static_cast<long>(v)) + " in layer " + std::to_string(layer) +
                     " belongs to no segment");
    const Segment& seg = segments[it->second];
    std::uint16_t& at = voxels[voxel];
    if (at == 0 || at == brain || at == seg.table_value) {
      if (at == 0 || seg.table_value != brain) at = seg.table_value;
      in_voxel[it->second] = voxel;
      return;
    }
    if (seg.table_value == brain) return;
    if (overlaps++ == 0) {
      std::size_t other = 0;
      for (std::size_t s = 0; s < segments.size(); ++s)
        if (segments[s].table_value == at && segments[s].layer != layer && in_voxel[s] == voxel) other = s;
      first_overlap = {other, it->second};
    }
  });
  if (voxels.empty()) voxels.resize(out.grid.voxel_count(), 0);
  if (overlaps > 0)
    fail(path, "segments \"" + segments[first_overlap.first].name + "\" and \"" + segments[first_overlap.second].name +
                   "\" overlap in " + std::to_string(overlaps) +
                   " voxels: which structure a voxel is decides its material and whether it is resected; resolve the "
                   "overlap in the segment editor (only the brain may contain the others)");
  return out;
}

void write_nrrd_scalar(const fs::path& path, const ImageF& image) {
  write(path, header(image.grid, "float", false),
        std::string(reinterpret_cast<const char*>(image.voxels.data()), image.voxels.size() * sizeof(float)));
}

void write_nrrd_labels(const fs::path& path, const LabelImage& labels) {
  write(path, header(labels.grid, "unsigned short", false),
        std::string(reinterpret_cast<const char*>(labels.voxels.data()), labels.voxels.size() * 2));
}

void write_nrrd_displacement(const fs::path& path, const VectorImage3& field) {
  std::vector<float> lps;
  lps.reserve(field.vectors.size() * 3);
  for (const auto& v : field.vectors) {
    const Eigen::Vector3d u = ras_to_lps(v.cast<double>());
    lps.insert(lps.end(), {static_cast<float>(u.x()), static_cast<float>(u.y()), static_cast<float>(u.z())});
  }
  write(path, header(field.grid, "float", true) + "displacement field type:=resampling\n",
        std::string(reinterpret_cast<const char*>(lps.data()), lps.size() * sizeof(float)));
}

}  // namespace brainshift
