#pragma once
// Who may send what (PROTOCOL.md section 13). The role of a request comes from
// the connection it arrived on (the ZAP User-Id of a CURVE peer), never from
// anything the client wrote in the request.
#include <optional>
#include <string>
#include <string_view>

#include "protocol/message_types.h"

namespace brainshift::server {

enum class Role { scanner, viewer, admin };
std::string_view to_string(Role r);
std::optional<Role> role_from_string(std::string_view s);

// The sender of one request, as the transport established it.
struct Peer {
  bool authenticated = false;  // false: no CURVE (loopback only)
  std::optional<Role> role;    // authenticated: from the ZAP User-Id; nullopt = none (refused)
  std::string name;            // allow-list name, for the log

  static Peer unauthenticated_local() { return {}; }
  static Peer from_zap(const std::optional<std::string>& user_id, const std::optional<std::string>& name);
  std::string describe() const;  // "scanner \"or1\"", "unauthenticated local client"
};

// nullopt when the peer may send this request; otherwise why not (the
// message of the `unauthorised` reply). Without CURVE every loopback client
// acts as admin except for shutdown, which needs allow_unauthenticated_shutdown.
std::optional<std::string> refusal(const Peer& peer, protocol::MessageType type,
                                   bool allow_unauthenticated_shutdown);

}  // namespace brainshift::server
