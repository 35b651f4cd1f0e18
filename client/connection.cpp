#include "connection.h"

#include <unistd.h>

#include "protocol/error_codes.h"
#include "protocol/requests.h"
#include "protocol/transport.h"

namespace brainshift::cli {

namespace {

// Why a server may stay silent; a refused CURVE handshake looks exactly like
// an absent server to the client (libzmq retries it quietly).
constexpr std::chrono::milliseconds kMonitorSlice{100};

std::string silence_hint(const CurveKeys& curve) {
  if (curve)
    return "is brainshiftd running there, and does it accept this client? A key missing from the server's "
           "allow-list, or a wrong --server-key, is refused at the CURVE handshake without any answer "
           "(see --server, --key, --server-key, --timeout)";
  return "is brainshiftd running there? A server with CURVE authentication answers only clients that "
         "give --key and --server-key (see --server, --timeout)";
}

}  // namespace

Connection::Connection(std::string endpoint, std::chrono::milliseconds timeout, CurveKeys curve)
    : endpoint_(std::move(endpoint)), timeout_(timeout), curve_(std::move(curve)), context_(1) {
  reconnect();
}

Connection::~Connection() = default;

void Connection::reconnect() {
  monitor_.reset();
  socket_ = std::make_unique<zmq::socket_t>(context_, zmq::socket_type::dealer);
  // Never block the exit on unsent requests to a server that is not there.
  socket_->set(zmq::sockopt::linger, 0);
  if (curve_) protocol::curve::set_client_options(*socket_, *curve_);
  monitor_ = std::make_unique<HandshakeMonitor>(*socket_, endpoint_, curve_.has_value());
  try {
    socket_->connect(endpoint_);
  } catch (const zmq::error_t& e) {
    throw CommandError(kExitUsage, "bad endpoint \"" + endpoint_ + "\": " + e.what());
  }
}

std::string Connection::next_request_id() {
  return "cli-" + std::to_string(::getpid()) + "-" + std::to_string(++counter_);
}

protocol::Message Connection::call_raw(const protocol::Message& request) {
  namespace t = protocol::transport;
  t::send_request(*socket_, request);
  const auto deadline = std::chrono::steady_clock::now() + timeout_;
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) break;
    if (auto why = monitor_->refusal()) {
      reconnect();
      throw CommandError(kExitUnreachable, *why);
    }
    std::optional<protocol::Message> reply;
    try {
      // In slices, so that a refused handshake ends the wait early.
      reply = t::receive_reply(*socket_, protocol::Limits::client_inbound(), std::min(left, kMonitorSlice));
    } catch (const protocol::ProtocolError& e) {
      throw CommandError(kExitError, std::string("unreadable reply from the server: ") + e.what());
    }
    if (!reply) continue;
    // A late reply to an earlier, timed-out request is not ours.
    if (reply->request_id() == request.request_id() || reply->request_id().empty()) return *reply;
  }
  // A fresh socket drops whatever the server may still send for this request.
  reconnect();
  throw CommandError(kExitUnreachable, "no reply from " + endpoint_ + " within " +
                                           std::to_string(timeout_.count() / 1000.0).substr(0, 5) +
                                           " s: " + silence_hint(curve_));
}

protocol::Message Connection::call(const protocol::Message& request) {
  protocol::Message reply = call_raw(request);
  if (reply.type() == protocol::MessageType::kError) {
    const protocol::ErrorInfo e = protocol::parse_error_reply(reply);
    throw CommandError(e.code == protocol::ErrorCode::kScanFailed ? kExitScanFailed : kExitError,
                       "server error " + std::string(protocol::to_string(e.code)) + ": " + e.message);
  }
  return reply;
}

EventStream::EventStream(const std::string& endpoint, const std::string& topic_prefix, const CurveKeys& curve)
    : endpoint_(endpoint), context_(1), socket_(context_, zmq::socket_type::sub) {
  socket_.set(zmq::sockopt::linger, 0);
  if (curve) protocol::curve::set_client_options(socket_, *curve);
  monitor_ = std::make_unique<HandshakeMonitor>(socket_, endpoint_, curve.has_value());
  socket_.set(zmq::sockopt::subscribe, topic_prefix);
  try {
    socket_.connect(endpoint);
  } catch (const zmq::error_t& e) {
    throw CommandError(kExitUsage, "bad events endpoint \"" + endpoint + "\": " + e.what());
  }
}

std::optional<protocol::Message> EventStream::next(std::chrono::milliseconds timeout) {
  if (auto why = monitor_->refusal()) throw CommandError(kExitUnreachable, "events: " + *why);
  return protocol::transport::receive_event(socket_, protocol::Limits::client_inbound(), timeout);
}

}  // namespace brainshift::cli
