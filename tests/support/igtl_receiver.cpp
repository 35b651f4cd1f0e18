#include "igtl_receiver.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <stdexcept>
#include <string>

#include <igtlMessageHeader.h>
#include <igtl_header.h>

namespace brainshift::test {

IgtlReceiver::IgtlReceiver(int port, std::chrono::milliseconds timeout) : socket_(igtl::ClientSocket::New()) {
  if (socket_->ConnectToServer("127.0.0.1", port) != 0)
    throw std::runtime_error("cannot connect to OpenIGTLink port " + std::to_string(port));
  socket_->SetReceiveTimeout(static_cast<int>(timeout.count()));
}

std::optional<IgtlReceived> IgtlReceiver::next() {
  auto header = igtl::MessageHeader::New();
  header->InitPack();
  if (socket_->Receive(header->GetPackPointer(), header->GetPackSize()) != header->GetPackSize()) return std::nullopt;
  header->Unpack();
  IgtlReceived r;
  r.type = header->GetDeviceType();
  r.device = header->GetDeviceName();
  header->GetTimeStamp(&r.seconds, &r.fraction);
  r.body_size = static_cast<std::uint64_t>(header->GetBodySizeToRead());
  if (r.body_size == 0) return r;  // a null-body reply: the data asked for is not there
  if (r.type == "IMAGE") r.message = igtl::ImageMessage::New().GetPointer();
  else if (r.type == "POLYDATA") r.message = igtl::PolyDataMessage::New().GetPointer();
  else if (r.type == "STATUS") r.message = igtl::StatusMessage::New().GetPointer();
  else if (r.type == "IMGMETA") r.message = igtl::ImageMetaMessage::New().GetPointer();
  else if (r.type == "LBMETA") r.message = igtl::LabelMetaMessage::New().GetPointer();
  else if (r.body_size <= 4096) {
    r.raw_body.resize(static_cast<std::size_t>(r.body_size));
    if (socket_->Receive(r.raw_body.data(), static_cast<int>(r.body_size)) != static_cast<int>(r.body_size))
      return std::nullopt;
    return r;
  } else throw std::runtime_error("unexpected OpenIGTLink message type " + r.type);
  r.message->SetMessageHeader(header);
  r.message->AllocatePack();
  const int body = r.message->GetPackBodySize();
  if (body > 0 && socket_->Receive(r.message->GetPackBodyPointer(), body) != body) return std::nullopt;
  if ((r.message->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) == 0)
    throw std::runtime_error(r.type + " " + r.device + ": body does not unpack (CRC)");
  return r;
}

std::vector<IgtlReceived> IgtlReceiver::next_result() {
  std::vector<IgtlReceived> out;
  for (;;) {
    auto m = next();
    if (!m) throw std::runtime_error("no complete OpenIGTLink result arrived (" + std::to_string(out.size()) +
                                     " message(s) before the timeout)");
    out.push_back(*m);
    if (out.back().type == "STATUS") return out;
  }
}

void IgtlReceiver::send_query(const std::string& type, const std::string& device) {
  igtl_header h{};
  h.version = IGTL_HEADER_VERSION;
  std::memcpy(h.name, type.data(), std::min<std::size_t>(type.size(), IGTL_HEADER_TYPE_SIZE));
  std::memcpy(h.device_name, device.data(), std::min<std::size_t>(device.size(), IGTL_HEADER_NAME_SIZE));
  igtl_header_convert_byte_order(&h);  // body size 0, CRC of nothing 0
  if (socket_->Send(&h, IGTL_HEADER_SIZE) != 1) throw std::runtime_error("cannot send " + type);
}

Eigen::Matrix4d igtl_world_from_voxel(igtl::ImageMessage& image) {
  int dims[3];
  float spacing[3];
  image.GetDimensions(dims);
  image.GetSpacing(spacing);
  igtl::Matrix4x4 m;
  image.GetMatrix(m);
  Eigen::Matrix4d w = Eigen::Matrix4d::Identity();
  Eigen::Vector3d centre(m[0][3], m[1][3], m[2][3]);
  for (int a = 0; a < 3; ++a) {
    const Eigen::Vector3d axis = Eigen::Vector3d(m[0][a], m[1][a], m[2][a]).normalized();
    w.block<3, 1>(0, a) = axis * spacing[a];
    centre -= axis * spacing[a] * (dims[a] - 1) / 2.0;
  }
  w.block<3, 1>(0, 3) = centre;
  return w;
}

int raw_igtl_connect(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) throw std::runtime_error("socket()");
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(static_cast<std::uint16_t>(port));
  inet_pton(AF_INET, "127.0.0.1", &a.sin_addr);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
    ::close(fd);
    throw std::runtime_error("connect to 127.0.0.1:" + std::to_string(port));
  }
  return fd;
}

}  // namespace brainshift::test
