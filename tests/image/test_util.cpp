#include "test_util.h"

#include <nifti/nifti1.h>
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
  nifti_2_header b{};
  b.sizeof_hdr = sizeof b;
  std::memcpy(b.magic, "n+2\0\r\n\032\n", 8);
  b.datatype = a.datatype;
  b.bitpix = a.bitpix;
  for (int d = 0; d < 8; ++d) {
    b.dim[d] = a.dim[d];
    b.pixdim[d] = a.pixdim[d];
  }
  b.intent_p1 = a.intent_p1;
  b.intent_p2 = a.intent_p2;
  b.intent_p3 = a.intent_p3;
  b.vox_offset = sizeof b + 4;
  b.scl_slope = a.scl_slope;
  b.scl_inter = a.scl_inter;
  b.qform_code = a.qform_code;
  b.sform_code = a.sform_code;
  b.quatern_b = a.quatern_b;
  b.quatern_c = a.quatern_c;
  b.quatern_d = a.quatern_d;
  b.qoffset_x = a.qoffset_x;
  b.qoffset_y = a.qoffset_y;
  b.qoffset_z = a.qoffset_z;
  for (int c = 0; c < 4; ++c) {
    b.srow_x[c] = a.srow_x[c];
    b.srow_y[c] = a.srow_y[c];
    b.srow_z[c] = a.srow_z[c];
  }
  b.xyzt_units = a.xyzt_units;
  b.intent_code = a.intent_code;
  std::memcpy(b.intent_name, a.intent_name, sizeof b.intent_name);
  std::memcpy(b.descrip, a.descrip, sizeof b.descrip);
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
