#pragma once
// Multipart send/receive of protocol messages over ZeroMQ (cppzmq). Kept apart
// from the codec so that message.h/requests.h need no ZeroMQ at all.
//
// Envelope rule (PROTOCOL.md, "Framing"): every request starts with an empty
// delimiter frame, as a REQ socket sends it. REQ adds and strips it itself;
// for DEALER sockets these functions add and strip it, so REQ and DEALER
// clients look the same to the ROUTER.
#include <chrono>
#include <optional>
#include <string>
#include <vector>

#include <zmq.hpp>

#include "protocol/message.h"

namespace brainshift::protocol::transport {

using Wire = std::vector<std::string>;

// Routing frames a ROUTER received before the delimiter (inclusive); they are
// sent back unchanged in front of the reply.
struct Envelope {
  std::vector<std::string> routing;
};
// Connection properties libzmq attaches to every message of a CURVE peer,
// set by the server's ZAP handler (PROTOCOL.md section 13): the role is the
// ZAP User-Id, the allow-list name travels as this metadata property.
inline constexpr const char* kClientNameProperty = "X-Client-Name";

struct RoutedRequest {
  Envelope envelope;
  Wire wire;  // [header][frames...], ready for decode()
  // From the connection, never from the header: absent without CURVE/ZAP.
  std::optional<std::string> user_id;
  std::optional<std::string> client_name;
};

// Waits until the socket has a message to read; false on timeout.
bool wait_readable(zmq::socket_ref socket, std::chrono::milliseconds timeout);

// Reads one whole multipart message; nullopt if none arrived within timeout
// (a negative timeout blocks).
std::optional<Wire> receive_wire(zmq::socket_ref socket, std::chrono::milliseconds timeout);
void send_wire(zmq::socket_ref socket, const Wire& wire);

// ROUTER side. A message without a delimiter cannot be answered (the routing
// frames are unknown), so it is returned with an empty wire: the caller
// drops it and logs it; ProtocolError is never thrown from here.
std::optional<RoutedRequest> receive_request(zmq::socket_ref router,
                                             std::chrono::milliseconds timeout);
void send_reply(zmq::socket_ref router, const Envelope& envelope, const Message& reply);

// Client side (DEALER or REQ).
void send_request(zmq::socket_ref client, const Message& request);
// nullopt on timeout; otherwise decode(), which throws ProtocolError on a bad
// reply. Error replies are returned as messages (see throw_if_error).
std::optional<Message> receive_reply(zmq::socket_ref client, const Limits& limits,
                                     std::chrono::milliseconds timeout);

// PUB/SUB: [topic = event type][header][frames...].
void publish(zmq::socket_ref pub, const Message& event);
// Throws ProtocolError(kBadHeader) when the topic disagrees with the header type.
std::optional<Message> receive_event(zmq::socket_ref sub, const Limits& limits,
                                     std::chrono::milliseconds timeout);

// Sets ZMQ_MAXMSGSZ to hard_frame_cap_bytes: libzmq then disconnects a peer
// sending a larger frame before allocating it. Frames between
// limits.max_frame_bytes and the cap still reach decode() and get a too_large
// reply, which is why the cap defaults to twice the larger of the header and
// frame limits (the header frame must pass the cap too). The cap is enforced
// by libzmq's stream decoder, so it applies to tcp:// and ipc://, not inproc://.
void apply_hard_frame_cap(zmq::socket_ref socket, const Limits& limits,
                          std::optional<std::int64_t> hard_frame_cap_bytes = std::nullopt);

}  // namespace brainshift::protocol::transport
