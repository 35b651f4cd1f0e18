#pragma once
// Versions of the wire protocol and of the timing-log line schema.
// Bump kProtocolVersion only for changes an old peer would misread (see
// PROTOCOL.md, "Versioning"); adding optional fields does not bump it.

namespace brainshift::protocol {

inline constexpr int kProtocolVersion = 1;
inline constexpr int kTimingLogVersion = 1;

}  // namespace brainshift::protocol
