#pragma once
// A 3D Slicer stand-in for the tests: an OpenIGTLink client built on the
// library's own classes (igtl::ClientSocket, igtl::MessageHeader and the
// message Unpack with CRC check), and the geometry a receiver derives from an
// IMAGE, computed the way Slicer's OpenIGTLinkIF does.
#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <igtlClientSocket.h>
#include <igtlImageMessage.h>
#include <igtlImageMetaMessage.h>
#include <igtlLabelMetaMessage.h>
#include <igtlMessageBase.h>
#include <igtlPolyDataMessage.h>
#include <igtlStatusMessage.h>

namespace brainshift::test {

struct IgtlReceived {
  std::string type, device;
  unsigned seconds = 0, fraction = 0;  // header time stamp
  // An unpacked ImageMessage, PolyDataMessage, StatusMessage, ImageMetaMessage
  // or LabelMetaMessage; null for a null body or another type (raw_body).
  igtl::MessageBase::Pointer message;
  std::uint64_t body_size = 0;
  std::string raw_body;  // the body of a type not unpacked (e.g. RTS_IMAGE)
  igtl::ImageMessage* image() const { return dynamic_cast<igtl::ImageMessage*>(message.GetPointer()); }
  igtl::ImageMetaMessage* image_meta() const { return dynamic_cast<igtl::ImageMetaMessage*>(message.GetPointer()); }
  igtl::LabelMetaMessage* label_meta() const { return dynamic_cast<igtl::LabelMetaMessage*>(message.GetPointer()); }
  igtl::PolyDataMessage* polydata() const { return dynamic_cast<igtl::PolyDataMessage*>(message.GetPointer()); }
  igtl::StatusMessage* status() const { return dynamic_cast<igtl::StatusMessage*>(message.GetPointer()); }
};

class IgtlReceiver {
 public:
  // Connects to 127.0.0.1:port; throws when it cannot.
  IgtlReceiver(int port, std::chrono::milliseconds timeout);
  // The next message; nullopt when none arrived in time or the server closed.
  // Throws std::runtime_error when a body fails to unpack (CRC mismatch).
  std::optional<IgtlReceived> next();
  // Messages up to and including the next STATUS (one whole result); throws
  // when it does not arrive in time.
  std::vector<IgtlReceived> next_result();
  // Sends a header-only message (a query: GET_IMAGE, STT_IMAGE, ...).
  void send_query(const std::string& type, const std::string& device);
  igtl::ClientSocket& socket() { return *socket_; }

 private:
  igtl::ClientSocket::Pointer socket_;
};

// IJK -> RAS of an IMAGE, as Slicer's OpenIGTLinkIF builds it: unit axes
// times spacing, the matrix's origin moved from the volume's centre to voxel
// (0,0,0).
Eigen::Matrix4d igtl_world_from_voxel(igtl::ImageMessage& image);

// A plain TCP connection to 127.0.0.1:port (its file descriptor), for peers
// that misbehave; throws std::runtime_error when it cannot connect.
int raw_igtl_connect(int port);

}  // namespace brainshift::test
