#pragma once
// How a fuzz input becomes a multipart ZeroMQ message: the frames are joined
// by a separator line, the first frame is the JSON header. A textual separator
// keeps the seed files readable (and is in message.dict, so the fuzzer adds and
// removes frames as easily as it edits bytes).
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace brainshift::fuzz {

inline constexpr std::string_view kFrameSeparator = "\n--frame--\n";

inline std::vector<std::string> split_frames(std::string_view data) {
  std::vector<std::string> wire;
  for (;;) {
    const auto at = data.find(kFrameSeparator);
    wire.emplace_back(data.substr(0, at));
    if (at == std::string_view::npos) break;
    data.remove_prefix(at + kFrameSeparator.size());
  }
  return wire;
}

inline std::string join_frames(const std::vector<std::string>& wire) {
  std::string out;
  for (std::size_t i = 0; i < wire.size(); ++i) {
    if (i > 0) out += kFrameSeparator;
    out += wire[i];
  }
  return out;
}

}  // namespace brainshift::fuzz
