#include "test_util.h"

#include <nifti2_io.h>  // niftilib (libnifti2): the reference conversion
#include <zlib.h>

#include <fstream>
#include <stdexcept>

namespace brainshift::test {

std::string gzip(const std::string& raw) {
  z_stream zs{};
  deflateInit2(&zs, 6, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY);
  std::string out(deflateBound(&zs, raw.size()), '\0');
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(raw.data()));
  zs.avail_in = static_cast<uInt>(raw.size());
  zs.next_out = reinterpret_cast<Bytef*>(out.data());
  zs.avail_out = static_cast<uInt>(out.size());
  if (deflate(&zs, Z_FINISH) != Z_STREAM_END) throw std::runtime_error("deflate failed");
  out.resize(zs.total_out);
  deflateEnd(&zs);
  return out;
}

std::string gunzip(const std::string& gz) {
  z_stream zs{};
  inflateInit2(&zs, 15 + 32);
  std::string out;
  char buf[1 << 16];
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(gz.data()));
  zs.avail_in = static_cast<uInt>(gz.size());
  int rc = Z_OK;
  while (rc == Z_OK) {
    zs.next_out = reinterpret_cast<Bytef*>(buf);
    zs.avail_out = sizeof(buf);
    rc = inflate(&zs, Z_NO_FLUSH);
    out.append(buf, sizeof(buf) - zs.avail_out);
  }
  inflateEnd(&zs);
  if (rc != Z_STREAM_END) throw std::runtime_error("inflate failed");
  return out;
}

void write_bytes(const std::filesystem::path& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (!out) throw std::runtime_error("cannot write " + path.string());
}

nifti_2_header nifti2_header_of(const std::string& nifti1_raw) {
  nifti_1_header a;
  if (nifti1_raw.size() < sizeof a) throw std::runtime_error("nifti2_header_of: not a NIfTI-1 file");
  std::memcpy(&a, nifti1_raw.data(), sizeof a);
  // The reference library converts (NIfTI-1 header -> nifti_image -> NIfTI-2
  // header), so the tests do not check our reader against our own widening.
  nifti_image* nim = nifti_convert_n1hdr2nim(a, nullptr);
  if (nim == nullptr) throw std::runtime_error("nifti2_header_of: niftilib refused the NIfTI-1 header");
  nim->nifti_type = NIFTI_FTYPE_NIFTI2_1;
  nifti_2_header b{};
  const int rc = nifti_convert_nim2n2hdr(nim, &b);
  nifti_image_free(nim);
  if (rc != 0) throw std::runtime_error("nifti2_header_of: niftilib cannot make a NIfTI-2 header");
  std::memcpy(b.magic, "n+2\0\r\n\032\n", 8);
  b.vox_offset = sizeof b + 4;  // niftilib sets it only when it writes a file
  return b;
}

std::string_view nifti1_voxels(const std::string& nifti1_raw) {
  nifti_1_header a;
  std::memcpy(&a, nifti1_raw.data(), sizeof a);
  return std::string_view(nifti1_raw).substr(static_cast<std::size_t>(a.vox_offset));
}

std::string nifti2_file(const nifti_2_header& h, std::string_view voxels) {
  std::string out(sizeof h + 4, '\0');
  std::memcpy(out.data(), &h, sizeof h);
  out += voxels;
  return out;
}

}  // namespace brainshift::test
