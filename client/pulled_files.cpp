#include "pulled_files.h"

#include <zlib.h>

#include <stdexcept>

#include "protocol/media.h"
#include "protocol/result_outputs.h"

namespace brainshift::cli {

std::string gzip_bytes(std::string_view bytes, int level) {
  z_stream z{};
  // windowBits 15 + 16: a gzip header and trailer instead of a zlib one.
  if (deflateInit2(&z, level, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY) != Z_OK)
    throw std::runtime_error("zlib: deflateInit2 failed");
  std::string out(deflateBound(&z, static_cast<uLong>(bytes.size())) + 32, '\0');
  z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(bytes.data()));
  z.avail_in = static_cast<uInt>(bytes.size());
  z.next_out = reinterpret_cast<Bytef*>(out.data());
  z.avail_out = static_cast<uInt>(out.size());
  const int rc = deflate(&z, Z_FINISH);
  const std::size_t written = z.total_out;
  deflateEnd(&z);
  if (rc != Z_STREAM_END) throw std::runtime_error("zlib: deflate did not finish (" + std::to_string(rc) + ")");
  out.resize(written);
  return out;
}

PulledFile pulled_file_for(const protocol::Frame& frame) {
  PulledFile f{protocol::file_for_frame(frame.name), frame.bytes};
  const std::string_view gz = ".nii.gz";
  const bool wants_gzip =
      f.name.size() > gz.size() && std::string_view(f.name).substr(f.name.size() - gz.size()) == gz;
  if (wants_gzip && frame.media_type == protocol::media::kNifti) f.bytes = gzip_bytes(frame.bytes);
  return f;
}

}  // namespace brainshift::cli
