#pragma once
// VTK XML (ASCII) writers for meshes and surfaces, readable by ParaView and
// 3D Slicer, plus a reader for the .vtp files written here (clients, tests).
// Coordinates are written as stored: world RAS+ mm, and every file says so in
// a VTK field-data string array SPACE = "RAS", which 3D Slicer reads (without
// it Slicer assumes LPS and shows the model mirrored in x and y).
#include <filesystem>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "core/tet_mesh.h"

namespace brainshift {

// The frame of every coordinate written by this module.
inline constexpr const char* kModelSpace = "RAS";

// The SPACE field-data value of a VTK XML file ("RAS", "LPS"), "" when absent.
std::string vtk_space(std::string_view xml);

// Optional per-vertex arrays of a .vtp (each must have one entry per vertex).
struct SurfaceAttributes {
  std::vector<std::pair<std::string, std::vector<Eigen::Vector3d>>> vectors;
  std::vector<std::pair<std::string, std::vector<double>>> scalars;
};

// Unstructured grid: cell data "label"; point data "displacement_mm" when given.
void write_vtu(const std::filesystem::path& path, const TetMesh& mesh,
               const std::vector<Eigen::Vector3d>* node_displacements_mm = nullptr);
std::string vtu_bytes(const TetMesh& mesh, const std::vector<Eigen::Vector3d>* node_displacements_mm = nullptr);

// PolyData of triangles; mesh_node (when present) is written as point data
// "mesh_node" so that read_vtp restores it. Every file carries per-vertex unit
// normals (vertex_normals: outward for a model, RAS like the points) as the
// point-data array "Normals" (Float32, 4 decimals: enough to shade with and
// ~12 ms on a 200k-vertex brain model), declared the PointData Normals attribute so VTK
// and 3D Slicer shade with them instead of recomputing their own.
void write_vtp(const std::filesystem::path& path, const TriSurface& surface,
               const SurfaceAttributes& attributes = {});
std::string vtp_bytes(const TriSurface& surface, const SurfaceAttributes& attributes = {});

// Reads points, triangles and "mesh_node" of a .vtp as written above, in RAS:
// a file whose SPACE is LPS is converted, one without SPACE is taken as RAS.
// Throws InputError naming `name` on anything it cannot parse.
TriSurface read_vtp_bytes(std::string_view bytes, std::string_view name = "<memory>");
TriSurface read_vtp(const std::filesystem::path& path);
// The "Normals" point data of a .vtp, in RAS (converted like the points);
// empty when the file has none. InputError on a malformed array.
std::vector<Eigen::Vector3d> read_vtp_normals(std::string_view bytes, std::string_view name = "<memory>");

}  // namespace brainshift
