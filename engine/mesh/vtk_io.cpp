#include "mesh/vtk_io.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <charconv>
#include <concepts>
#include <fstream>
#include <sstream>
#include <string_view>

#include "core/errors.h"
#include "core/file_bytes.h"
#include "field/lps.h"

namespace brainshift {
namespace {

// Text output for the ASCII VTK writers. std::to_chars gives the shortest
// text that reads back to the same double (exact round trip) and is ~10x
// faster than an ostream at max_digits10: the daemon encodes every model of
// every scan on the latency path.
class TextOut {
 public:
  TextOut& operator<<(std::string_view s) {
    text_.append(s);
    return *this;
  }
  TextOut& operator<<(const char* s) { return *this << std::string_view(s); }
  TextOut& operator<<(char c) {
    text_.push_back(c);
    return *this;
  }
  TextOut& operator<<(std::floating_point auto v) { return put(static_cast<double>(v)); }
  TextOut& operator<<(std::integral auto v) { return put(v); }
  std::string str() && { return std::move(text_); }
  // A value in [-1, 1] to 4 decimals, through integer formatting: normals
  // need no more for shading, and the shortest-double text of 3 components
  // per vertex nearly doubled the encoding of a brain model (0.14 -> 0.26 s).
  TextOut& unit_fixed4(double v) {
    const long q = std::lround(std::clamp(v, -1.0, 1.0) * 10000.0);
    if (q < 0) text_.push_back('-');
    const long a = q < 0 ? -q : q;
    put(a / 10000);
    char digits[5] = {'.', '0', '0', '0', '0'};
    for (long r = a % 10000, d = 4; d > 0; --d, r /= 10) digits[d] = static_cast<char>('0' + r % 10);
    text_.append(digits, 5);
    return *this;
  }

 private:
  template <class T>
  TextOut& put(T v) {
    char buffer[32];
    const auto [end, ec] = std::to_chars(buffer, buffer + sizeof buffer, v);
    text_.append(buffer, end);
    return *this;
  }
  std::string text_;
};

constexpr const char* kNormalsArray = "Normals";

void write_points(TextOut& os, const std::vector<Eigen::Vector3d>& points) {
  os << "<Points>\n<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n";
  for (const auto& p : points) os << p.x() << ' ' << p.y() << ' ' << p.z() << '\n';
  os << "</DataArray>\n</Points>\n";
}

void write_vectors(TextOut& os, const std::string& name, const std::vector<Eigen::Vector3d>& v) {
  os << "<DataArray type=\"Float64\" Name=\"" << name << "\" NumberOfComponents=\"3\" format=\"ascii\">\n";
  for (const auto& p : v) os << p.x() << ' ' << p.y() << ' ' << p.z() << '\n';
  os << "</DataArray>\n";
}

// 3D Slicer reads a model without a SPACE field as LPS and negates x and y,
// so a RAS model would show mirrored left-right and front-back: every file
// written here names its frame. VTK stores an ASCII string array as the
// character codes of each string followed by a 0.
void write_space_field(TextOut& os) {
  os << "<FieldData>\n<Array type=\"String\" Name=\"SPACE\" NumberOfTuples=\"1\" format=\"ascii\">\n";
  for (char c : std::string_view(kModelSpace)) os << static_cast<int>(c) << ' ';
  os << "0\n</Array>\n</FieldData>\n";
}

void write_file(const std::filesystem::path& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  if (!out) throw InputError("cannot open " + path.string() + " for writing");
  out << bytes;
  if (!out) throw InputError("failed writing " + path.string());
}

void check_size(std::size_t got, std::size_t want, const std::string& what) {
  if (got != want) throw InputError(what + ": " + std::to_string(got) + " values for " + std::to_string(want) + " vertices");
}

// The text between the '>' of the first "<DataArray ... Name=name" after
// `from` and its "</DataArray>"; empty view when absent.
std::string_view data_array(std::string_view xml, std::size_t from, std::size_t to, std::string_view name_attr) {
  while (true) {
    const std::size_t tag = xml.find("<DataArray", from);
    if (tag == std::string_view::npos || tag >= to) return {};
    const std::size_t close = xml.find('>', tag);
    const std::size_t end = xml.find("</DataArray>", close);
    if (close == std::string_view::npos || end == std::string_view::npos) return {};
    const std::string_view head = xml.substr(tag, close - tag);
    if (name_attr.empty() || head.find(name_attr) != std::string_view::npos) return xml.substr(close + 1, end - close - 1);
    from = end;
  }
}

template <class T>
std::vector<T> parse_numbers(std::string_view text, std::string_view what, std::string_view name) {
  std::vector<T> values;
  const char* p = text.data();
  const char* const end = p + text.size();
  while (true) {
    while (p != end && std::isspace(static_cast<unsigned char>(*p))) ++p;
    if (p == end) return values;
    T v{};
    const auto [next, ec] = std::from_chars(p, end, v);
    if (ec != std::errc()) throw InputError(std::string(name) + ": bad number in " + std::string(what));
    values.push_back(v);
    p = next;
  }
}

std::size_t section(std::string_view xml, std::string_view tag, std::string_view name) {
  const std::size_t at = xml.find(tag);
  if (at == std::string_view::npos) throw InputError(std::string(name) + ": no " + std::string(tag) + " section (not a VTK PolyData file?)");
  return at;
}

// The frame a file names: true for LPS, false for RAS or none (files without
// SPACE are taken as RAS: this reader is for files written here, older ones
// lacked the field); InputError for any other frame.
bool file_is_lps(std::string_view xml, const std::string& who) {
  const std::string space = vtk_space(xml);
  if (!space.empty() && space != "RAS" && space != "LPS")
    throw InputError(who + ": unknown coordinate SPACE '" + space + "' (expected RAS or LPS)");
  return space == "LPS";
}

}  // namespace

std::string vtk_space(std::string_view xml) {
  const std::size_t field = xml.find("<FieldData>");
  if (field == std::string_view::npos) return "";
  const std::size_t end = xml.find("</FieldData>", field);
  std::size_t tag = xml.find("Name=\"SPACE\"", field);
  if (end == std::string_view::npos || tag == std::string_view::npos || tag > end) return "";
  const std::size_t open = xml.find('>', tag), close = xml.find("</Array>", tag);
  if (open == std::string_view::npos || close == std::string_view::npos || close > end) return "";
  std::string space;
  for (long long code : parse_numbers<long long>(xml.substr(open + 1, close - open - 1), "SPACE", "FieldData")) {
    if (code == 0) break;
    if (code < 32 || code > 126) return "";
    space.push_back(static_cast<char>(code));
  }
  return space;
}

std::string vtu_bytes(const TetMesh& mesh, const std::vector<Eigen::Vector3d>* displacements) {
  if (displacements) check_size(displacements->size(), mesh.node_count(), "write_vtu displacement");
  if (mesh.tet_labels.size() != mesh.tet_count()) throw InputError("write_vtu: tet_labels size differs from tet count");
  TextOut os;
  os << "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\">\n"
     << "<UnstructuredGrid>\n";
  write_space_field(os);
  os << "<Piece NumberOfPoints=\"" << mesh.node_count() << "\" NumberOfCells=\"" << mesh.tet_count() << "\">\n";
  if (displacements) {
    os << "<PointData Vectors=\"displacement_mm\">\n";
    write_vectors(os, "displacement_mm", *displacements);
    os << "</PointData>\n";
  }
  os << "<CellData Scalars=\"label\">\n<DataArray type=\"Int32\" Name=\"label\" format=\"ascii\">\n";
  for (int l : mesh.tet_labels) os << l << '\n';
  os << "</DataArray>\n</CellData>\n";
  write_points(os, mesh.nodes_mm);
  os << "<Cells>\n<DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">\n";
  for (const auto& t : mesh.tets) os << t[0] << ' ' << t[1] << ' ' << t[2] << ' ' << t[3] << '\n';
  os << "</DataArray>\n<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">\n";
  for (std::size_t t = 1; t <= mesh.tet_count(); ++t) os << 4 * t << '\n';
  os << "</DataArray>\n<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n";
  for (std::size_t t = 0; t < mesh.tet_count(); ++t) os << "10\n";  // VTK_TETRA
  os << "</DataArray>\n</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>\n";
  return std::move(os).str();
}

void write_vtu(const std::filesystem::path& path, const TetMesh& mesh, const std::vector<Eigen::Vector3d>* displacements) {
  write_file(path, vtu_bytes(mesh, displacements));
}

std::string vtp_bytes(const TriSurface& s, const SurfaceAttributes& attributes) {
  const std::size_t nv = s.vertices_mm.size();
  if (!s.mesh_node.empty()) check_size(s.mesh_node.size(), nv, "write_vtp mesh_node");
  for (const auto& [name, v] : attributes.vectors) check_size(v.size(), nv, "write_vtp " + name);
  for (const auto& [name, v] : attributes.scalars) check_size(v.size(), nv, "write_vtp " + name);
  for (const auto& [name, v] : attributes.vectors)
    if (name == kNormalsArray) throw InputError("write_vtp: \"Normals\" is written by the writer itself");
  TextOut os;
  os << "<?xml version=\"1.0\"?>\n<VTKFile type=\"PolyData\" version=\"0.1\" byte_order=\"LittleEndian\">\n"
     << "<PolyData>\n";
  write_space_field(os);
  os << "<Piece NumberOfPoints=\"" << nv << "\" NumberOfVerts=\"0\" NumberOfLines=\"0\" NumberOfStrips=\"0\" NumberOfPolys=\""
     << s.triangles.size() << "\">\n<PointData Normals=\"" << kNormalsArray << "\">\n";
  // Float32 at 4 decimals: a shading direction needs no more, and it keeps
  // the text (and the daemon's encoding time on the latency path) small.
  os << "<DataArray type=\"Float32\" Name=\"" << kNormalsArray << "\" NumberOfComponents=\"3\" format=\"ascii\">\n";
  for (const Eigen::Vector3d& n : vertex_normals(s)) {
    os.unit_fixed4(n.x()) << ' ';
    os.unit_fixed4(n.y()) << ' ';
    os.unit_fixed4(n.z()) << '\n';
  }
  os << "</DataArray>\n";
  if (!s.mesh_node.empty()) {
    os << "<DataArray type=\"Int32\" Name=\"mesh_node\" format=\"ascii\">\n";
    for (int n : s.mesh_node) os << n << '\n';
    os << "</DataArray>\n";
  }
  for (const auto& [name, v] : attributes.vectors) write_vectors(os, name, v);
  for (const auto& [name, v] : attributes.scalars) {
    os << "<DataArray type=\"Float64\" Name=\"" << name << "\" format=\"ascii\">\n";
    for (double x : v) os << x << '\n';
    os << "</DataArray>\n";
  }
  os << "</PointData>\n";
  write_points(os, s.vertices_mm);
  os << "<Polys>\n<DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">\n";
  for (const auto& t : s.triangles) os << t[0] << ' ' << t[1] << ' ' << t[2] << '\n';
  os << "</DataArray>\n<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">\n";
  for (std::size_t t = 1; t <= s.triangles.size(); ++t) os << 3 * t << '\n';
  os << "</DataArray>\n</Polys>\n</Piece>\n</PolyData>\n</VTKFile>\n";
  return std::move(os).str();
}

void write_vtp(const std::filesystem::path& path, const TriSurface& surface, const SurfaceAttributes& attributes) {
  write_file(path, vtp_bytes(surface, attributes));
}

TriSurface read_vtp_bytes(std::string_view xml, std::string_view name) {
  const std::string who(name);
  if (xml.find("type=\"PolyData\"") == std::string_view::npos) throw InputError(who + ": not a VTK XML PolyData file");
  if (xml.find("format=\"ascii\"") == std::string_view::npos || xml.find("format=\"binary\"") != std::string_view::npos ||
      xml.find("format=\"appended\"") != std::string_view::npos)
    throw InputError(who + ": only ASCII VTK XML is supported");
  const std::size_t points_at = section(xml, "<Points>", name), polys_at = section(xml, "<Polys>", name);
  const auto coords = parse_numbers<double>(data_array(xml, points_at, xml.size(), ""), "Points", name);
  const auto conn = parse_numbers<long long>(data_array(xml, polys_at, xml.size(), "Name=\"connectivity\""), "connectivity", name);
  const auto offsets = parse_numbers<long long>(data_array(xml, polys_at, xml.size(), "Name=\"offsets\""), "offsets", name);
  if (coords.size() % 3 != 0) throw InputError(who + ": point coordinates are not triples");
  TriSurface s;
  for (std::size_t i = 0; i < coords.size(); i += 3) s.vertices_mm.emplace_back(coords[i], coords[i + 1], coords[i + 2]);
  long long previous = 0;
  for (long long end : offsets) {
    if (end - previous != 3 || end > static_cast<long long>(conn.size())) throw InputError(who + ": polygon is not a triangle");
    std::array<int, 3> t{};
    for (int a = 0; a < 3; ++a) {
      const long long v = conn[previous + a];
      if (v < 0 || v >= static_cast<long long>(s.vertices_mm.size())) throw InputError(who + ": vertex index out of range");
      t[a] = static_cast<int>(v);
    }
    s.triangles.push_back(t);
    previous = end;
  }
  if (previous != static_cast<long long>(conn.size())) throw InputError(who + ": connectivity and offsets disagree");
  if (file_is_lps(xml, who))
    for (auto& v : s.vertices_mm) v = lps_to_ras(v);
  const std::size_t pd = xml.find("<PointData");
  if (pd != std::string_view::npos && pd < points_at) {
    const auto nodes = data_array(xml, pd, points_at, "Name=\"mesh_node\"");
    if (nodes.data()) {
      for (long long n : parse_numbers<long long>(nodes, "mesh_node", name)) s.mesh_node.push_back(static_cast<int>(n));
      check_size(s.mesh_node.size(), s.vertices_mm.size(), who + " mesh_node");
    }
  }
  return s;
}

std::vector<Eigen::Vector3d> read_vtp_normals(std::string_view xml, std::string_view name) {
  const std::string who(name);
  const std::size_t pd = xml.find("<PointData");
  const std::size_t points_at = section(xml, "<Points>", name);
  std::vector<Eigen::Vector3d> normals;
  if (pd == std::string_view::npos || pd > points_at) return normals;
  const auto text = data_array(xml, pd, points_at, "Name=\"Normals\"");
  if (!text.data()) return normals;
  const auto values = parse_numbers<double>(text, "Normals", name);
  if (values.size() % 3 != 0) throw InputError(who + ": Normals are not triples");
  const bool lps = file_is_lps(xml, who);
  for (std::size_t i = 0; i < values.size(); i += 3) {
    const Eigen::Vector3d n(values[i], values[i + 1], values[i + 2]);
    normals.push_back(lps ? lps_to_ras(n) : n);
  }
  return normals;
}

TriSurface read_vtp(const std::filesystem::path& path) {
  return read_vtp_bytes(read_whole_file(path, "VTK file"), path.string());
}

}  // namespace brainshift
