#include "protocol/transport.h"

#include <iterator>

#include <zmq_addon.hpp>

namespace brainshift::protocol::transport {
namespace {

bool is_dealer(zmq::socket_ref s) { return s.get(zmq::sockopt::type) == ZMQ_DEALER; }

// A metadata property of the connection the message came through; nullopt
// when libzmq has none (e.g. User-Id without a ZAP handler).
std::optional<std::string> property(const zmq::message_t& m, const char* name) {
  const char* value = zmq_msg_gets(m.handle(), name);
  if (!value) return std::nullopt;
  return std::string(value);
}

std::optional<std::vector<zmq::message_t>> receive_parts(zmq::socket_ref socket,
                                                         std::chrono::milliseconds timeout) {
  if (timeout.count() >= 0 && !wait_readable(socket, timeout)) return std::nullopt;
  std::vector<zmq::message_t> parts;
  if (!zmq::recv_multipart(socket, std::back_inserter(parts))) return std::nullopt;
  return parts;
}

}  // namespace

bool wait_readable(zmq::socket_ref socket, std::chrono::milliseconds timeout) {
  zmq_pollitem_t item{socket.handle(), 0, ZMQ_POLLIN, 0};
  return zmq::poll(&item, 1, timeout) > 0 && (item.revents & ZMQ_POLLIN);
}

std::optional<Wire> receive_wire(zmq::socket_ref socket, std::chrono::milliseconds timeout) {
  auto parts = receive_parts(socket, timeout);
  if (!parts) return std::nullopt;
  Wire wire;
  wire.reserve(parts->size());
  for (auto& p : *parts) wire.emplace_back(p.to_string());
  return wire;
}

void send_wire(zmq::socket_ref socket, const Wire& wire) {
  for (std::size_t i = 0; i < wire.size(); ++i) {
    const auto flags = i + 1 < wire.size() ? zmq::send_flags::sndmore : zmq::send_flags::none;
    socket.send(zmq::buffer(wire[i]), flags);
  }
}

std::optional<RoutedRequest> receive_request(zmq::socket_ref router,
                                             std::chrono::milliseconds timeout) {
  auto parts = receive_parts(router, timeout);
  if (!parts) return std::nullopt;
  RoutedRequest req;
  // The ROUTER makes the identity frame itself, without metadata; the frames
  // that came over the connection carry it.
  if (!parts->empty()) {
    req.user_id = property(parts->back(), "User-Id");
    req.client_name = property(parts->back(), kClientNameProperty);
  }
  auto wire = std::optional<Wire>(std::in_place);
  wire->reserve(parts->size());
  for (auto& p : *parts) wire->emplace_back(p.to_string());
  // Identities are never empty, and neither is a JSON header, so the first
  // empty frame is the delimiter.
  std::size_t i = 0;
  while (i < wire->size() && !(*wire)[i].empty()) ++i;
  if (i == wire->size()) return req;  // no delimiter: unanswerable
  req.envelope.routing.assign(std::make_move_iterator(wire->begin()),
                              std::make_move_iterator(wire->begin() + i + 1));
  req.wire.assign(std::make_move_iterator(wire->begin() + i + 1),
                  std::make_move_iterator(wire->end()));
  return req;
}

void send_reply(zmq::socket_ref router, const Envelope& envelope, const Message& reply) {
  Wire wire = envelope.routing;
  for (auto& part : encode(reply)) wire.push_back(std::move(part));
  send_wire(router, wire);
}

void send_request(zmq::socket_ref client, const Message& request) {
  Wire wire;
  if (is_dealer(client)) wire.emplace_back();
  for (auto& part : encode(request)) wire.push_back(std::move(part));
  send_wire(client, wire);
}

std::optional<Message> receive_reply(zmq::socket_ref client, const Limits& limits,
                                     std::chrono::milliseconds timeout) {
  auto wire = receive_wire(client, timeout);
  if (!wire) return std::nullopt;
  if (is_dealer(client)) {
    if (wire->empty() || !wire->front().empty())
      throw ProtocolError(ErrorCode::kBadHeader, "reply lacks the empty delimiter frame");
    wire->erase(wire->begin());
  }
  return decode(std::move(*wire), limits);
}

void publish(zmq::socket_ref pub, const Message& event) {
  Wire wire{std::string(to_string(event.type()))};
  for (auto& part : encode(event)) wire.push_back(std::move(part));
  send_wire(pub, wire);
}

std::optional<Message> receive_event(zmq::socket_ref sub, const Limits& limits,
                                     std::chrono::milliseconds timeout) {
  auto wire = receive_wire(sub, timeout);
  if (!wire) return std::nullopt;
  if (wire->size() < 2) throw ProtocolError(ErrorCode::kBadHeader, "event without topic or header");
  const std::string topic = std::move(wire->front());
  wire->erase(wire->begin());
  Message m = decode(std::move(*wire), limits);
  if (to_string(m.type()) != topic)
    throw ProtocolError(ErrorCode::kBadHeader,
                        "event topic \"" + topic + "\" differs from its type \"" +
                            std::string(to_string(m.type())) + "\"");
  return m;
}

void apply_hard_frame_cap(zmq::socket_ref socket, const Limits& limits,
                          std::optional<std::int64_t> hard_frame_cap_bytes) {
  const auto largest = std::max(limits.max_frame_bytes, limits.max_header_bytes);
  socket.set(zmq::sockopt::maxmsgsize,
             hard_frame_cap_bytes.value_or(static_cast<std::int64_t>(largest) * 2));
}

}  // namespace brainshift::protocol::transport
