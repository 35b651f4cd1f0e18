#include "pulled_files.h"

#include "core/gzip.h"
#include "protocol/media.h"
#include "protocol/result_outputs.h"

namespace brainshift::cli {

PulledFile pulled_file_for(const protocol::Frame& frame) {
  PulledFile f{protocol::file_for_frame(frame.name), frame.bytes};
  const std::string_view gz = ".nii.gz";
  const bool wants_gzip =
      f.name.size() > gz.size() && std::string_view(f.name).substr(f.name.size() - gz.size()) == gz;
  if (wants_gzip && frame.media_type == protocol::media::kNifti) f.bytes = gzip_bytes(frame.bytes);
  return f;
}

}  // namespace brainshift::cli
