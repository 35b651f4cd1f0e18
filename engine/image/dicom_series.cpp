#include "image/dicom_series.h"

#include <dcmtk/config/osconfig.h>
#include <dcmtk/dcmdata/dcdeftag.h>
#include <dcmtk/dcmdata/dcfilefo.h>
#include <dcmtk/dcmdata/dcspchrs.h>
#include <dcmtk/dcmdata/dcxfer.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <optional>
#include <set>
#include <sstream>

#include "core/errors.h"
#include "field/lps.h"

namespace brainshift {
namespace fs = std::filesystem;
namespace {

// A folder is searched to this many files: a whole exam is a few thousand.
constexpr std::size_t kMaxFiles = 100000;
// Headers are read without element values above this size (pixel data stay on disk).
constexpr Uint32 kHeaderReadLength = 4096;

struct Slice {
  fs::path file;
  std::string series_uid, description, modality, patient_id;
  Eigen::Vector3d row_dir = Eigen::Vector3d::Zero(), col_dir = Eigen::Vector3d::Zero();  // LPS
  Eigen::Vector3d position_lps = Eigen::Vector3d::Zero();
  double row_spacing = 0, col_spacing = 0;  // PixelSpacing: between rows, between columns
  long rows = 0, cols = 0, frames = 1, instance = -1;
  double along_normal = 0;
};

std::string error_prefix(const fs::path& dir) { return "DICOM " + dir.string() + ": "; }

std::string text(DcmDataset& d, const DcmTagKey& tag) {
  OFString v;
  return d.findAndGetOFString(tag, v).good() ? std::string(v.c_str()) : std::string();
}

std::optional<double> number(DcmDataset& d, const DcmTagKey& tag, unsigned long pos = 0) {
  Float64 v = 0;
  if (d.findAndGetFloat64(tag, v, pos).bad() || !std::isfinite(v)) return std::nullopt;
  return v;
}

long integer(DcmDataset& d, const DcmTagKey& tag, long fallback) {
  OFString v;
  if (d.findAndGetOFString(tag, v).bad() || v.empty()) return fallback;
  try {
    return std::stol(v.c_str());
  } catch (const std::exception&) {
    return fallback;
  }
}

// PatientID in UTF-8, as the protocol carries it: converted from the
// character set the file declares (SpecificCharacterSet; a European site's
// ISO_IR 100 writes an umlaut as one byte), as written when it declares none
// or the conversion fails (a caller that needs text then says so).
std::string patient_id_utf8(DcmDataset& d) {
  const std::string raw = text(d, DCM_PatientID);
  OFString charset;
  if (std::all_of(raw.begin(), raw.end(), [](char c) { return static_cast<unsigned char>(c) < 0x80; }) ||
      d.findAndGetOFStringArray(DCM_SpecificCharacterSet, charset).bad() || charset.empty())
    return raw;
  DcmSpecificCharacterSet converter;
  OFString utf8;
  if (converter.selectCharacterSet(charset).bad() || converter.convertString(raw.c_str(), utf8).bad()) return raw;
  return std::string(utf8.c_str());
}

// Part-10 files only (the "DICM" preamble): anything else in the folder is skipped.
std::optional<Slice> read_header(const fs::path& file) {
  DcmFileFormat ff;
  if (ff.loadFile(file.c_str(), EXS_Unknown, EGL_noChange, kHeaderReadLength, ERM_fileOnly).bad()) return std::nullopt;
  DcmDataset& d = *ff.getDataset();
  Slice s;
  s.file = file;
  s.series_uid = text(d, DCM_SeriesInstanceUID);
  if (s.series_uid.empty() || !d.tagExists(DCM_PixelData)) return std::nullopt;  // not an image (e.g. a report)
  s.description = text(d, DCM_SeriesDescription);
  s.modality = text(d, DCM_Modality);
  s.patient_id = patient_id_utf8(d);
  for (int a = 0; a < 3; ++a) {
    s.row_dir[a] = number(d, DCM_ImageOrientationPatient, a).value_or(NAN);
    s.col_dir[a] = number(d, DCM_ImageOrientationPatient, a + 3).value_or(NAN);
    s.position_lps[a] = number(d, DCM_ImagePositionPatient, a).value_or(NAN);
  }
  s.row_spacing = number(d, DCM_PixelSpacing, 0).value_or(NAN);
  s.col_spacing = number(d, DCM_PixelSpacing, 1).value_or(NAN);
  s.rows = integer(d, DCM_Rows, 0);
  s.cols = integer(d, DCM_Columns, 0);
  s.frames = integer(d, DCM_NumberOfFrames, 1);
  s.instance = integer(d, DCM_InstanceNumber, -1);
  return s;
}

std::vector<Slice> read_headers(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) throw InputError(error_prefix(dir) + "not a folder");
  std::vector<fs::path> files;
  for (auto it = fs::recursive_directory_iterator(dir, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    if (files.size() == kMaxFiles)
      throw InputError(error_prefix(dir) + "more than " + std::to_string(kMaxFiles) + " files; give the series' folder");
    files.push_back(it->path());
  }
  if (ec) throw InputError(error_prefix(dir) + ec.message());
  std::sort(files.begin(), files.end());
  std::vector<Slice> slices;
  for (const auto& f : files)
    if (auto s = read_header(f)) slices.push_back(std::move(*s));
  if (slices.empty()) throw InputError(error_prefix(dir) + "no DICOM image files");
  return slices;
}

std::vector<DicomSeriesSummary> summarise(const std::vector<Slice>& slices) {
  std::map<std::string, DicomSeriesSummary> by_uid;
  for (const auto& s : slices) {
    auto& e = by_uid[s.series_uid];
    e.series_uid = s.series_uid;
    e.description = s.description;
    e.modality = s.modality;
    ++e.files;
  }
  std::vector<DicomSeriesSummary> out;
  for (auto& [uid, e] : by_uid) out.push_back(e);
  return out;
}

std::string series_list(const std::vector<DicomSeriesSummary>& all) {
  std::ostringstream os;
  for (const auto& s : all)
    os << "\n  " << s.series_uid << "  " << s.modality << "  " << s.files << " file(s)  \"" << s.description << "\"";
  return os.str();
}

std::string fmt(double v) {
  std::ostringstream os;
  os.precision(6);
  os << v;
  return os.str();
}

// Every slice of the series has the first one's size, spacing and orientation.
void check_alike(const fs::path& dir, const std::vector<Slice>& slices) {
  const Slice& f = slices.front();
  if (!f.row_dir.allFinite() || !f.col_dir.allFinite() || !f.position_lps.allFinite())
    throw InputError(error_prefix(dir) + f.file.filename().string() +
                     ": no ImageOrientationPatient / ImagePositionPatient (not a volume slice)");
  if (!(f.row_spacing > 0) || !(f.col_spacing > 0))
    throw InputError(error_prefix(dir) + f.file.filename().string() + ": no positive PixelSpacing");
  if (f.rows < 1 || f.cols < 1) throw InputError(error_prefix(dir) + f.file.filename().string() + ": no Rows/Columns");
  // ImageOrientationPatient is written with about 6 digits: 1e-3 tells a
  // rounded unit vector from a wrong one.
  if (std::abs(f.row_dir.norm() - 1) > 1e-3 || std::abs(f.col_dir.norm() - 1) > 1e-3 ||
      std::abs(f.row_dir.dot(f.col_dir)) > 1e-3)
    throw InputError(error_prefix(dir) + "ImageOrientationPatient is not two orthogonal unit vectors");
  for (const Slice& s : slices) {
    const std::string name = s.file.filename().string();
    if (s.frames != 1)
      throw InputError(error_prefix(dir) + name + ": " + std::to_string(s.frames) +
                       " frames; multi-frame (enhanced) objects are not read, export single-frame slices");
    if (s.rows != f.rows || s.cols != f.cols)
      throw InputError(error_prefix(dir) + name + ": " + std::to_string(s.cols) + "x" + std::to_string(s.rows) +
                       " pixels, the series' first slice has " + std::to_string(f.cols) + "x" + std::to_string(f.rows));
    if (std::abs(s.row_spacing - f.row_spacing) > 1e-4 * f.row_spacing ||
        std::abs(s.col_spacing - f.col_spacing) > 1e-4 * f.col_spacing)
      throw InputError(error_prefix(dir) + name + ": PixelSpacing differs from the first slice's");
    if (!s.row_dir.allFinite() || !s.col_dir.allFinite() || !s.position_lps.allFinite() ||
        (s.row_dir - f.row_dir).norm() > 1e-3 || (s.col_dir - f.col_dir).norm() > 1e-3)
      throw InputError(error_prefix(dir) + name +
                       ": ImageOrientationPatient differs from the first slice's (or is missing): not one volume");
    if (s.patient_id != f.patient_id)
      throw InputError(error_prefix(dir) + name + ": PatientID \"" + s.patient_id + "\", the first slice's \"" +
                       f.patient_id + "\": slices of two patients are not one volume");
  }
}

// Missing InstanceNumbers between the smallest and the largest present.
std::string missing_instances(const std::vector<Slice>& slices) {
  std::set<long> present;
  for (const auto& s : slices)
    if (s.instance >= 0) present.insert(s.instance);
  if (present.size() < 2 || *present.rbegin() - *present.begin() > 100000) return "";
  std::string out;
  for (long n = *present.begin(); n <= *present.rbegin(); ++n)
    if (!present.count(n)) out += (out.empty() ? "" : ", ") + std::to_string(n);
  return out.empty() ? "" : " (InstanceNumber " + out + " missing)";
}

// The slices sorted along the normal, stacked uniformly; returns the spacing.
double check_stack(const fs::path& dir, std::vector<Slice>& slices, const Eigen::Vector3d& normal) {
  if (slices.size() < 2) throw InputError(error_prefix(dir) + "a single slice is not a volume");
  for (auto& s : slices) s.along_normal = s.position_lps.dot(normal);
  std::sort(slices.begin(), slices.end(), [](const Slice& a, const Slice& b) { return a.along_normal < b.along_normal; });
  const double n = static_cast<double>(slices.size() - 1);
  const double spacing = (slices.back().along_normal - slices.front().along_normal) / n;
  const double tol = dicom_slice_tolerance_mm(spacing);
  for (std::size_t k = 0; k + 1 < slices.size(); ++k) {
    const Slice &a = slices[k], &b = slices[k + 1];
    const double step = b.along_normal - a.along_normal;
    if (step < tol)
      throw InputError(error_prefix(dir) + a.file.filename().string() + " and " + b.file.filename().string() +
                       " are at one position (" + fmt(a.along_normal) + " mm along the normal): two series mixed, "
                       "or a file copied twice");
    const Eigen::Vector3d d = b.position_lps - a.position_lps;
    if ((d - d.dot(normal) * normal).norm() > tol)
      throw InputError(error_prefix(dir) + "the slice positions do not advance along the slice normal (offset " +
                       fmt((d - d.dot(normal) * normal).norm()) +
                       " mm in plane per slice): gantry tilt or a sheared stack is not read; resample it first");
  }
  double smallest = slices[1].along_normal - slices[0].along_normal;
  for (std::size_t k = 1; k + 1 < slices.size(); ++k)
    smallest = std::min(smallest, slices[k + 1].along_normal - slices[k].along_normal);
  for (std::size_t k = 0; k + 1 < slices.size(); ++k) {
    const double step = slices[k + 1].along_normal - slices[k].along_normal;
    if (std::abs(step - smallest) <= dicom_slice_tolerance_mm(smallest)) continue;
    const double ratio = step / smallest;
    std::string why = "non-uniform slice spacing: " + slices[k].file.filename().string() + " and " +
                      slices[k + 1].file.filename().string() + " are " + fmt(step) + " mm apart, the closest slices " +
                      fmt(smallest) + " mm";
    if (std::abs(ratio - std::round(ratio)) < 0.05)
      why += ": " + std::to_string(std::lround(ratio) - 1) + " slice(s) missing between " + fmt(slices[k].along_normal) +
             " and " + fmt(slices[k + 1].along_normal) + " mm along the normal" + missing_instances(slices);
    throw InputError(error_prefix(dir) + why);
  }
  return spacing;
}

// The stored values of one slice, rescaled.
void read_pixels(const fs::path& dir, const Slice& s, float* out) {
  DcmFileFormat ff;
  if (ff.loadFile(s.file.c_str()).bad()) throw InputError(error_prefix(dir) + s.file.filename().string() + ": unreadable");
  DcmDataset& d = *ff.getDataset();
  const std::string name = s.file.filename().string();
  const E_TransferSyntax xfer = d.getOriginalXfer();
  if (DcmXfer(xfer).isEncapsulated())
    throw InputError(error_prefix(dir) + name + ": compressed pixel data (" + DcmXfer(xfer).getXferName() +
                     "); decompress the series first (e.g. DCMTK's dcmdjpeg)");
  if (integer(d, DCM_SamplesPerPixel, 1) != 1)
    throw InputError(error_prefix(dir) + name + ": colour pixels; a grey-scale series is needed");
  const long allocated = integer(d, DCM_BitsAllocated, 0), stored = integer(d, DCM_BitsStored, allocated);
  const long high = integer(d, DCM_HighBit, stored - 1);
  const bool is_signed = integer(d, DCM_PixelRepresentation, 0) == 1;
  if ((allocated != 8 && allocated != 16) || stored < 1 || stored > allocated || high != stored - 1)
    throw InputError(error_prefix(dir) + name + ": " + std::to_string(allocated) + "-bit pixels with " +
                     std::to_string(stored) + " stored bits, high bit " + std::to_string(high) +
                     "; 8 or 16 bits, high bit = stored bits - 1 are read");
  const double slope = number(d, DCM_RescaleSlope).value_or(1.0), intercept = number(d, DCM_RescaleIntercept).value_or(0.0);
  if (slope == 0) throw InputError(error_prefix(dir) + name + ": RescaleSlope 0");
  const std::size_t count = static_cast<std::size_t>(s.rows) * static_cast<std::size_t>(s.cols);
  const auto value = [&](std::uint32_t raw) {
    raw &= (stored == 32 ? 0xffffffffu : ((1u << stored) - 1));
    long v = static_cast<long>(raw);
    if (is_signed && (raw >> (stored - 1)) & 1u) v -= 1L << stored;  // two's complement of stored bits
    return static_cast<float>(v * slope + intercept);
  };
  unsigned long n = 0;
  if (allocated == 16) {
    const Uint16* p = nullptr;
    if (d.findAndGetUint16Array(DCM_PixelData, p, &n).bad() || !p || n < count)
      throw InputError(error_prefix(dir) + name + ": pixel data shorter than Rows x Columns");
    for (std::size_t i = 0; i < count; ++i) out[i] = value(p[i]);
  } else {
    const Uint8* p = nullptr;
    if (d.findAndGetUint8Array(DCM_PixelData, p, &n).bad() || !p || n < count)
      throw InputError(error_prefix(dir) + name + ": pixel data shorter than Rows x Columns");
    for (std::size_t i = 0; i < count; ++i) out[i] = value(p[i]);
  }
}

}  // namespace

double dicom_slice_tolerance_mm(double slice_spacing_mm) {
  return Grid3::kSameGridVoxelFraction * std::abs(slice_spacing_mm);
}

std::vector<DicomSeriesSummary> list_dicom_series(const fs::path& dir) { return summarise(read_headers(dir)); }

ImageF read_dicom_series(const fs::path& dir, const std::string& series_uid, std::size_t max_image_bytes,
                         std::string* patient_id) {
  std::vector<Slice> all = read_headers(dir);
  const auto series = summarise(all);
  std::string uid = series_uid;
  if (uid.empty()) {
    if (series.size() > 1)
      throw InputError(error_prefix(dir) + std::to_string(series.size()) +
                       " series; choose one by its SeriesInstanceUID (--series):" + series_list(series));
    uid = series.front().series_uid;
  }
  std::vector<Slice> slices;
  for (auto& s : all)
    if (s.series_uid == uid) slices.push_back(std::move(s));
  if (slices.empty()) throw InputError(error_prefix(dir) + "no series " + uid + "; the folder holds:" + series_list(series));
  check_alike(dir, slices);
  if (patient_id) *patient_id = slices.front().patient_id;
  const Eigen::Vector3d row = slices.front().row_dir.normalized(), col = slices.front().col_dir.normalized();
  const Eigen::Vector3d normal = row.cross(col).normalized();
  const double spacing = check_stack(dir, slices, normal);

  Grid3 grid;
  grid.dims = {static_cast<int>(slices.front().cols), static_cast<int>(slices.front().rows),
               static_cast<int>(slices.size())};
  const double bytes = 4.0 * static_cast<double>(grid.voxel_count());
  if (bytes > static_cast<double>(max_image_bytes))
    throw InputError(error_prefix(dir) + "the series holds " + fmt(bytes / 1e6) + " MB of voxels, more than the " +
                     fmt(max_image_bytes / 1e6) + " MB allowed");
  // Column index i runs along the row direction, spaced by the distance
  // between columns (PixelSpacing's second value), row index j along the
  // column direction.
  Eigen::Matrix4d lps = Eigen::Matrix4d::Identity();
  lps.block<3, 1>(0, 0) = row * slices.front().col_spacing;
  lps.block<3, 1>(0, 1) = col * slices.front().row_spacing;
  lps.block<3, 1>(0, 2) = normal * spacing;
  lps.block<3, 1>(0, 3) = slices.front().position_lps;
  grid.world_from_voxel = ras_world_from_lps_world_matrix(lps);

  ImageF image(grid);
  const std::size_t per_slice = static_cast<std::size_t>(grid.dims[0]) * grid.dims[1];
  for (std::size_t k = 0; k < slices.size(); ++k) read_pixels(dir, slices[k], image.voxels.data() + k * per_slice);
  return image;
}

}  // namespace brainshift
