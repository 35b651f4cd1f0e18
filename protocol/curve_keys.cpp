#include "protocol/curve_keys.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>

namespace brainshift::protocol::curve {
namespace fs = std::filesystem;
namespace {

constexpr std::size_t kZ85KeyLength = 40;
constexpr std::size_t kBinaryKeyLength = 32;
// The key files are tiny; anything bigger is not one of ours.
constexpr std::uintmax_t kMaxKeyFileBytes = 4096;

bool is_z85_char(char c) {
  static constexpr std::string_view alphabet =
      "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ.-:+=^!/*?&<>()[]{}@%$#";
  return alphabet.find(c) != std::string_view::npos;
}

std::string trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t\r");
  if (b == std::string::npos) return "";
  return s.substr(b, s.find_last_not_of(" \t\r") - b + 1);
}

// The one key line of a key file; what = "public" or "secret", for messages.
std::string key_from_text(const std::string& text, const fs::path& path, const char* what) {
  std::istringstream lines(text);
  std::string key;
  for (std::string line; std::getline(lines, line);) {
    line = trim(line);
    if (line.empty() || line[0] == '#') continue;
    if (!key.empty())
      throw KeyFileError(path.string() + ": more than one key line; a " + what + " key file holds one Z85 key");
    key = line;
  }
  if (key.empty()) throw KeyFileError(path.string() + ": no key in the file (expected a " + what + " Z85 key)");
  if (!is_z85_key(key))
    throw KeyFileError(path.string() + ": not a CURVE " + what + " key (expected 40 Z85 characters, got " +
                       std::to_string(key.size()) + " characters)");
  return key;
}

std::string read_small_file(const fs::path& path) {
  std::error_code ec;
  const auto size = fs::file_size(path, ec);
  if (ec) throw KeyFileError(path.string() + ": cannot read the key file (" + ec.message() + ")");
  if (size > kMaxKeyFileBytes)
    throw KeyFileError(path.string() + ": " + std::to_string(size) + " bytes is too big for a key file");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw KeyFileError(path.string() + ": cannot open the key file");
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

void write_exclusive(const fs::path& path, const std::string& text, mode_t mode) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, mode);
  if (fd < 0)
    throw KeyFileError(path.string() + ": cannot create (" + std::strerror(errno) +
                       "); an existing key is never overwritten");
  // The umask may only have removed bits; set exactly what we mean.
  const bool ok = ::fchmod(fd, mode) == 0 &&
                  ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size()) && ::fsync(fd) == 0;
  const int saved = errno;
  ::close(fd);
  if (!ok) {
    ::unlink(path.c_str());
    throw KeyFileError(path.string() + ": cannot write (" + std::strerror(saved) + ")");
  }
}

}  // namespace

bool available() { return zmq_has("curve") != 0; }

KeyPair generate_key_pair() {
  std::array<char, kZ85KeyLength + 1> pub{}, sec{};
  if (zmq_curve_keypair(pub.data(), sec.data()) != 0)
    throw std::runtime_error("zmq_curve_keypair failed: this libzmq was built without CURVE (libsodium)");
  return {std::string(pub.data(), kZ85KeyLength), std::string(sec.data(), kZ85KeyLength)};
}

std::string public_from_secret(const std::string& secret_z85) {
  if (!is_z85_key(secret_z85)) throw KeyFileError("not a CURVE secret key");
  std::array<char, kZ85KeyLength + 1> pub{};
  if (zmq_curve_public(pub.data(), secret_z85.c_str()) != 0)
    throw std::runtime_error("zmq_curve_public failed: this libzmq was built without CURVE (libsodium)");
  return std::string(pub.data(), kZ85KeyLength);
}

bool is_z85_key(std::string_view text) {
  if (text.size() != kZ85KeyLength) return false;
  for (char c : text)
    if (!is_z85_char(c)) return false;
  // Every 5 characters must encode a value below 2^32.
  std::array<std::uint8_t, kBinaryKeyLength> out{};
  const std::string z(text);
  return zmq_z85_decode(out.data(), z.c_str()) != nullptr;
}

std::string z85_to_binary(const std::string& z85) {
  std::array<std::uint8_t, kBinaryKeyLength> out{};
  if (!is_z85_key(z85) || !zmq_z85_decode(out.data(), z85.c_str())) throw KeyFileError("not a Z85 CURVE key");
  return std::string(reinterpret_cast<const char*>(out.data()), out.size());
}

std::string binary_to_z85(std::string_view binary32) {
  if (binary32.size() != kBinaryKeyLength) throw KeyFileError("a CURVE key has 32 bytes");
  std::array<char, kZ85KeyLength + 1> out{};
  zmq_z85_encode(out.data(), reinterpret_cast<const std::uint8_t*>(binary32.data()), binary32.size());
  return std::string(out.data(), kZ85KeyLength);
}

std::string fingerprint(std::string_view public_z85) { return std::string(public_z85.substr(0, 8)); }

fs::path public_key_path(const std::string& prefix) { return prefix + ".key"; }
fs::path secret_key_path(const std::string& prefix) { return prefix + ".key_secret"; }

std::string read_public_key_file(const fs::path& path) {
  return key_from_text(read_small_file(path), path, "public");
}

std::string read_secret_key_file(const fs::path& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0)
    throw KeyFileError(path.string() + ": cannot read the secret key file (" + std::strerror(errno) + ")");
  if (!S_ISREG(st.st_mode)) throw KeyFileError(path.string() + ": a secret key must be a regular file");
  // Another user could replace a key they own (ssh refuses those too).
  if (st.st_uid != ::geteuid() && st.st_uid != 0)
    throw KeyFileError(path.string() + ": owned by uid " + std::to_string(st.st_uid) +
                       ", not by this user (uid " + std::to_string(::geteuid()) + ") or root");
  if ((st.st_mode & 077) != 0) {
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
    throw KeyFileError(path.string() + ": permissions " + mode +
                       " are too open; a secret key must be accessible by its owner only (chmod 600 " +
                       path.string() + ")");
  }
  return key_from_text(read_small_file(path), path, "secret");
}

KeyPair read_key_pair(const std::string& prefix) {
  KeyPair pair{read_public_key_file(public_key_path(prefix)), read_secret_key_file(secret_key_path(prefix))};
  if (public_from_secret(pair.secret_z85) != pair.public_z85)
    throw KeyFileError(public_key_path(prefix).string() + " and " + secret_key_path(prefix).string() +
                       " are not one key pair");
  return pair;
}

KeyPair write_new_key_pair(const std::string& prefix) {
  const fs::path pub = public_key_path(prefix), sec = secret_key_path(prefix);
  for (const auto& p : {pub, sec})
    if (fs::exists(p)) throw KeyFileError(p.string() + " exists; an existing key is never overwritten");
  const KeyPair pair = generate_key_pair();
  write_exclusive(sec,
                  "# brainshift CURVE secret key (Z85). Keep it private: mode 0600, never copied off this machine.\n" +
                      pair.secret_z85 + "\n",
                  0600);
  try {
    write_exclusive(pub, "# brainshift CURVE public key (Z85); give it to the other end.\n" + pair.public_z85 + "\n",
                    0644);
  } catch (...) {
    ::unlink(sec.c_str());
    throw;
  }
  return pair;
}

void set_server_options(zmq::socket_ref socket, const std::string& secret_z85, const std::string& zap_domain) {
  socket.set(zmq::sockopt::curve_server, true);
  socket.set(zmq::sockopt::curve_secretkey, z85_to_binary(secret_z85));
  socket.set(zmq::sockopt::zap_domain, zap_domain);
}

void set_client_options(zmq::socket_ref socket, const ClientKeys& keys) {
  socket.set(zmq::sockopt::curve_serverkey, z85_to_binary(keys.server_public_z85));
  socket.set(zmq::sockopt::curve_publickey, z85_to_binary(keys.own.public_z85));
  socket.set(zmq::sockopt::curve_secretkey, z85_to_binary(keys.own.secret_z85));
}

}  // namespace brainshift::protocol::curve
