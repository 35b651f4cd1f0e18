#pragma once
// A 3D Slicer stand-in for the tests: an OpenIGTLink client built on the
// library's own classes (igtl::ClientSocket, igtl::MessageHeader and the
// message Unpack with CRC check), and the geometry a receiver derives from an
// IMAGE, computed the way Slicer's OpenIGTLinkIF does.
#include <chrono>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <igtlClientSocket.h>
#include <igtlImageMessage.h>
#include <igtlMessageBase.h>
#include <igtlPolyDataMessage.h>
#include <igtlStatusMessage.h>

namespace brainshift::test {

struct IgtlReceived {
  std::string type, device;
  unsigned seconds = 0, fraction = 0;  // header time stamp
  igtl::MessageBase::Pointer message;  // an unpacked ImageMessage, PolyDataMessage or StatusMessage
  igtl::ImageMessage* image() const { return dynamic_cast<igtl::ImageMessage*>(message.GetPointer()); }
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
