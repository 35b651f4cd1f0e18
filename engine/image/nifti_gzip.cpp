// gzip for NIfTI: a bounded sequential inflater and a one-shot deflater.
#include "image/nifti_gzip.h"

#include <algorithm>
#include <array>
#include <cstring>

#include "core/errors.h"

namespace brainshift::nifti_detail {
namespace {

constexpr std::size_t kChunk = 1u << 30;  // zlib counts in 32-bit uInt

[[noreturn]] void fail(std::string_view name, const std::string& what) {
  throw InputError(std::string(name) + ": " + what);
}

}  // namespace

ByteStream::ByteStream(std::string_view bytes, std::string_view name) : in_(bytes), name_(name) {
  gzip_ = bytes.size() >= 2 && static_cast<unsigned char>(bytes[0]) == 0x1f &&
          static_cast<unsigned char>(bytes[1]) == 0x8b;
  if (gzip_) {
    std::memset(&zs_, 0, sizeof(zs_));
    if (inflateInit2(&zs_, 15 + 32) != Z_OK) fail(name_, "cannot initialise zlib");
    zs_.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(in_.data()));
    zs_.avail_in = static_cast<uInt>(std::min<std::size_t>(in_.size(), kChunk));
    consumed_ = zs_.avail_in;
  }
}

ByteStream::~ByteStream() {
  if (gzip_) inflateEnd(&zs_);
}

void ByteStream::verify_to_end(std::size_t budget) {
  std::array<char, 1 << 16> scratch;
  std::size_t extra = 0;
  for (std::size_t n; (n = read(scratch.data(), scratch.size())) > 0;) {
    extra += n;
    if (extra > budget)
      fail(name_, "gzip stream holds more than the limit of decompressed bytes after the voxel data");
  }
  if (!ended_)
    fail(name_, "truncated gzip stream: it stops before its end-of-stream trailer, so its checksum cannot be verified");
}

std::size_t ByteStream::read(char* dst, std::size_t n) {
  if (!gzip_) {
    const std::size_t got = std::min(n, in_.size() - pos_);
    std::memcpy(dst, in_.data() + pos_, got);
    pos_ += got;
    return got;
  }
  return inflate_into(dst, n);
}

std::size_t ByteStream::inflate_into(char* dst, std::size_t n) {
  std::size_t got = 0;
  while (got < n && !finished_) {
    zs_.next_out = reinterpret_cast<Bytef*>(dst + got);
    zs_.avail_out = static_cast<uInt>(std::min(n - got, kChunk));
    const uInt before = zs_.avail_out;
    const int rc = inflate(&zs_, Z_NO_FLUSH);
    got += before - zs_.avail_out;
    if (zs_.avail_in == 0 && consumed_ < in_.size()) refill();
    if (rc == Z_STREAM_END) {  // the member's CRC-32 and length matched
      // Concatenated gzip members are legal; continue with the next one.
      // Bytes after the last member that are not gzip are ignored, as gzip(1) does.
      const bool next_member = zs_.avail_in >= 2 && zs_.next_in[0] == 0x1f && zs_.next_in[1] == 0x8b;
      if (!next_member) {
        finished_ = ended_ = true;
        break;
      }
      inflateReset(&zs_);
      continue;
    }
    if (rc == Z_BUF_ERROR) {  // no progress possible: input exhausted mid-stream
      if (zs_.avail_in == 0 && consumed_ >= in_.size()) {
        finished_ = true;
        break;
      }
      continue;
    }
    if (rc != Z_OK) fail(name_, std::string("corrupt gzip data (") + (zs_.msg ? zs_.msg : "zlib error") + ")");
  }
  return got;
}

void ByteStream::refill() {
  zs_.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(in_.data() + consumed_));
  zs_.avail_in = static_cast<uInt>(std::min(in_.size() - consumed_, kChunk));
  consumed_ += zs_.avail_in;
}

}  // namespace brainshift::nifti_detail
