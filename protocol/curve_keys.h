#pragma once
// ZeroMQ CURVE keys (PROTOCOL.md section 13): generation, key files and the
// socket options of the two ends. Shared by brainshiftd and the client.
//
// Key files hold one Z85 key (40 characters) on a line; blank lines and lines
// starting with '#' are ignored. `brainshift keygen --out P` writes
// P.key (public, shareable) and P.key_secret (mode 0600). A secret key file
// that its group or other users may access, or that another user owns, is
// refused, as ssh refuses such a private key.
#include <filesystem>
#include <stdexcept>
#include <string>
#include <string_view>

#include <zmq.hpp>

namespace brainshift::protocol::curve {

// A key file that is missing, unreadable, malformed or too open.
class KeyFileError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct KeyPair {
  std::string public_z85;  // 40 Z85 characters
  std::string secret_z85;  // 40 Z85 characters; never logged or sent
};

// What a client needs to talk CURVE to a server.
struct ClientKeys {
  std::string server_public_z85;
  KeyPair own;
};

// libzmq was built with CURVE (libsodium); Debian's is.
bool available();
KeyPair generate_key_pair();
std::string public_from_secret(const std::string& secret_z85);

// 40 characters of the Z85 alphabet that decode to 32 bytes.
bool is_z85_key(std::string_view text);
std::string z85_to_binary(const std::string& z85);     // 32 bytes; throws KeyFileError when not a key
std::string binary_to_z85(std::string_view binary32);  // 40 characters

// The first 8 characters of the Z85 public key: enough to tell keys apart in
// a log line, and a public key is no secret anyway.
std::string fingerprint(std::string_view public_z85);

std::string read_public_key_file(const std::filesystem::path& path);
// Refuses (KeyFileError) a file with any group/other permission bit, or one
// owned by another user than this one or root.
std::string read_secret_key_file(const std::filesystem::path& path);
// PREFIX.key_secret and PREFIX.key, checked to belong together.
KeyPair read_key_pair(const std::string& prefix);
// Writes PREFIX.key_secret (0600, created exclusively) and PREFIX.key (0644);
// refuses to overwrite either.
KeyPair write_new_key_pair(const std::string& prefix);
std::filesystem::path public_key_path(const std::string& prefix);
std::filesystem::path secret_key_path(const std::string& prefix);

// Socket options. The server end takes its secret key and a ZAP domain (the
// ZAP handler sees the domain, so it can tell which socket a peer came to).
void set_server_options(zmq::socket_ref socket, const std::string& secret_z85, const std::string& zap_domain);
void set_client_options(zmq::socket_ref socket, const ClientKeys& keys);

}  // namespace brainshift::protocol::curve
