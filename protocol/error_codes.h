#pragma once
// Typed protocol errors. The code is what a client branches on; the message is
// for the human at the console and names the field or frame that is wrong.
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>

namespace brainshift::protocol {

enum class ErrorCode {
  kMalformedJson,        // frame 0 is not a JSON object
  kVersionMismatch,      // "v" missing, not an integer, or not kProtocolVersion
  kUnknownType,          // "type" names no message of this protocol version
  kBadHeader,            // a common header field (request_id, frames manifest) is missing or ill-typed
  kFrameCountMismatch,   // binary frames received != frames declared in the header
  kFrameSizeMismatch,    // a frame's byte size != the size declared for it
  kTooLarge,             // a frame, the header or the whole message exceeds a configured limit
  kInvalidRequest,       // a type-specific field or frame is missing or has a bad value
  kBusy,                 // queue full or a conflicting job is running; retry later
  kNotFound,             // unknown scan_id
  kNotReady,             // no preop loaded yet, or the scan's result is not computed yet
  kScanFailed,           // the scan's registration failed; message says why
  kConflict,             // client_scan_id reused for different data
  kUnauthorised,         // the client's role does not allow this request
  kInternal,             // server fault; the request may be retried once
};

std::string_view to_string(ErrorCode code);
std::optional<ErrorCode> error_code_from_string(std::string_view name);
// Whether repeating the same request later can succeed without changing it.
bool is_retryable(ErrorCode code);

// Thrown by the codec and the typed parsers. request_id is filled whenever it
// could be read, so the server can still echo it in the error reply.
class ProtocolError : public std::runtime_error {
 public:
  ProtocolError(ErrorCode code, const std::string& message,
                std::optional<std::string> request_id = std::nullopt)
      : std::runtime_error(message), code_(code), request_id_(std::move(request_id)) {}
  ErrorCode code() const { return code_; }
  const std::optional<std::string>& request_id() const { return request_id_; }
  void set_request_id(std::string id) { request_id_ = std::move(id); }

 private:
  ErrorCode code_;
  std::optional<std::string> request_id_;
};

}  // namespace brainshift::protocol
