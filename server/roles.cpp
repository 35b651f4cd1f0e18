#include "server/roles.h"

namespace brainshift::server {
using protocol::MessageType;

std::string_view to_string(Role r) {
  switch (r) {
    case Role::scanner: return "scanner";
    case Role::viewer: return "viewer";
    case Role::admin: return "admin";
  }
  return "?";
}

std::optional<Role> role_from_string(std::string_view s) {
  for (Role r : {Role::scanner, Role::viewer, Role::admin})
    if (to_string(r) == s) return r;
  return std::nullopt;
}

Peer Peer::from_zap(const std::optional<std::string>& user_id, const std::optional<std::string>& name) {
  Peer p;
  p.authenticated = true;
  if (user_id) p.role = role_from_string(*user_id);
  p.name = name.value_or("");
  return p;
}

std::string Peer::describe() const {
  if (!authenticated) return "unauthenticated local client";
  if (!role) return "CURVE client without a role";
  return std::string(to_string(*role)) + " \"" + name + "\"";
}

namespace {

// The table of PROTOCOL.md section 13.
bool role_may_send(Role role, MessageType type) {
  switch (type) {
    case MessageType::kStatus:
    case MessageType::kScanList:
    case MessageType::kLabelsGet:
    case MessageType::kScanResult: return true;
    case MessageType::kScanPush: return role == Role::scanner || role == Role::admin;
    case MessageType::kPreopLoad:
    case MessageType::kShutdown: return role == Role::admin;
    default: return true;  // not a request: the handler answers unknown_type
  }
}

}  // namespace

std::optional<std::string> refusal(const Peer& peer, MessageType type, bool allow_unauthenticated_shutdown) {
  const std::string what(protocol::to_string(type));
  if (!peer.authenticated) {
    if (type == MessageType::kShutdown && !allow_unauthenticated_shutdown)
      return "shutdown needs an admin key (CURVE); this server takes no unauthenticated shutdown "
             "([security] allow_unauthenticated_shutdown is false)";
    return std::nullopt;
  }
  if (!peer.role) return "this connection carries no role; every request is refused";
  if (role_may_send(*peer.role, type)) return std::nullopt;
  return "role " + std::string(to_string(*peer.role)) + " (\"" + peer.name + "\") may not send " + what;
}

}  // namespace brainshift::server
