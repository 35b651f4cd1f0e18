#pragma once
// The one encoder of a registration's outputs, used by `brainshift register`
// (written as a folder) and by the daemon (kept as bytes, served and stored).
// Files are named by protocol/result_outputs.h, the table of every name a
// result part goes by.
#include <filesystem>
#include <functional>
#include <map>
#include <mutex>
#include <string>

#include "core/label_table.h"
#include "pipeline/engine_session.h"

namespace brainshift {

// gzip: register's files (field.nii.gz, ...). plain: the daemon's stored
// names (field.nii, ...), for latency; the client gzips when it writes them.
enum class ImageEncoding { gzip, plain };

// file name -> bytes
using EncodedOutputs = std::map<std::string, std::string>;

// The parts on the latency path: the field, the warped image and labels, the
// models and timings.json. The field (half of the bytes) is encoded on a
// second thread.
EncodedOutputs encode_scan_outputs(const ScanResult& result, ImageEncoding images);

struct DeferredOutputOptions {
  bool itk_single_precision = false;  // field.h5 parameters as float: as field.nii holds them, half the bytes
  // What report.png names and colours (the registration's label table) and
  // the id in its title.
  const LabelTable* label_table = nullptr;
  std::string scan_id;
  // Held while HDF5 encodes field.h5 when other threads use HDF5 too (the
  // library is not thread-safe in this build; the daemon's store is one).
  std::mutex* hdf5_mutex = nullptr;
  // uncertainty.nii: plain for the daemon's store, gzipped by register.
  ImageEncoding images = ImageEncoding::plain;
  // false: leave report.png out, for a caller that draws it later (the
  // daemon draws it after the uncertainty map, so that it shows the map).
  bool report = true;
};

// The deferred parts (made off the latency path, in this order):
// metrics.json, uncertainty.nii (when the result has its map), field.h5 and,
// with an intraop image, report.png. The report
// needs the quality metrics already in result.metrics. Each is handed to add
// as soon as it is ready.
using OutputFn = std::function<void(const std::string& name, std::string bytes)>;
void encode_deferred_outputs(const ScanResult& result, const ImageF* intraop_t1, const DeferredOutputOptions& options,
                             const OutputFn& add);

// What `brainshift register --out DIR` writes: every part, images gzipped.
// All files go to a temporary sibling folder first that is renamed into
// place, so a failure never leaves half-written outputs.
void write_scan_outputs(const ScanResult& result, const ImageF* intraop_t1, const std::filesystem::path& out_dir,
                        const DeferredOutputOptions& options);

}  // namespace brainshift
