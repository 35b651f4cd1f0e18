// CURVE keys (protocol/curve_keys.h): key files as `brainshift keygen` writes
// them, the refusals of malformed and too open files, and a real CURVE
// handshake over tcp loopback with keys read back from the files.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "protocol/curve_keys.h"
#include "temp_dir.h"
#include "protocol/requests.h"
#include "protocol/transport.h"

namespace curve = brainshift::protocol::curve;
namespace bp = brainshift::protocol;
namespace tp = brainshift::protocol::transport;
namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {

class KeyDir : public ::testing::Test {
 protected:
  std::string prefix(const std::string& name) const { return (dir_ / name).string(); }
  fs::path write(const std::string& name, const std::string& text, fs::perms perms = fs::perms::owner_read |
                                                                                   fs::perms::owner_write) const {
    const fs::path p = dir_ / name;
    std::ofstream(p) << text;
    fs::permissions(p, perms);
    return p;
  }
  // The message of the KeyFileError `fn` throws ("" when none).
  template <class Fn>
  static std::string refusal(Fn&& fn) {
    try {
      fn();
    } catch (const curve::KeyFileError& e) {
      return e.what();
    }
    return "";
  }
  brainshift::test::TempDir tmp_{"keys"};
  const fs::path& dir_ = tmp_.path();
};

unsigned mode_of(const fs::path& p) {
  struct stat st {};
  EXPECT_EQ(::stat(p.c_str(), &st), 0);
  return st.st_mode & 0777;
}

TEST(CurveKeys, LibzmqHasCurveAndPairsBelongTogether) {
  ASSERT_TRUE(curve::available()) << "Debian's libzmq5 is built with libsodium";
  const curve::KeyPair a = curve::generate_key_pair(), b = curve::generate_key_pair();
  EXPECT_TRUE(curve::is_z85_key(a.public_z85));
  EXPECT_TRUE(curve::is_z85_key(a.secret_z85));
  EXPECT_NE(a.public_z85, b.public_z85);
  EXPECT_EQ(curve::public_from_secret(a.secret_z85), a.public_z85);
  EXPECT_EQ(curve::binary_to_z85(curve::z85_to_binary(a.public_z85)), a.public_z85);
  EXPECT_EQ(curve::z85_to_binary(a.public_z85).size(), 32u);
  EXPECT_EQ(curve::fingerprint(a.public_z85), a.public_z85.substr(0, 8));
}

TEST(CurveKeys, Z85Validation) {
  const std::string good = curve::generate_key_pair().public_z85;
  EXPECT_FALSE(curve::is_z85_key(good.substr(0, 39)));
  EXPECT_FALSE(curve::is_z85_key(good + "0"));
  EXPECT_FALSE(curve::is_z85_key(std::string(39, 'a') + "\""));  // '"' is not in the alphabet
  EXPECT_FALSE(curve::is_z85_key(std::string(39, 'a') + " "));
  EXPECT_FALSE(curve::is_z85_key("#####################################(((("));
  EXPECT_THROW(curve::z85_to_binary("short"), curve::KeyFileError);
  EXPECT_THROW(curve::binary_to_z85("31 bytes are not a key........."), curve::KeyFileError);
}

TEST_F(KeyDir, WrittenPairReadsBackWithOwnerOnlySecret) {
  const curve::KeyPair written = curve::write_new_key_pair(prefix("scanner"));
  EXPECT_EQ(mode_of(curve::secret_key_path(prefix("scanner"))), 0600u);
  EXPECT_EQ(mode_of(curve::public_key_path(prefix("scanner"))), 0644u);
  const curve::KeyPair read = curve::read_key_pair(prefix("scanner"));
  EXPECT_EQ(read.public_z85, written.public_z85);
  EXPECT_EQ(read.secret_z85, written.secret_z85);
  // The public file never holds the secret.
  std::ifstream pub(curve::public_key_path(prefix("scanner")));
  const std::string pub_text((std::istreambuf_iterator<char>(pub)), {});
  EXPECT_EQ(pub_text.find(written.secret_z85), std::string::npos);
  // An existing key is never overwritten.
  EXPECT_NE(refusal([&] { curve::write_new_key_pair(prefix("scanner")); }).find("never overwritten"),
            std::string::npos);
  EXPECT_EQ(curve::read_key_pair(prefix("scanner")).secret_z85, written.secret_z85);
}

TEST_F(KeyDir, OpenSecretKeyFilesAreRefused) {
  const std::string key = curve::generate_key_pair().secret_z85;
  for (auto perms : {fs::perms::owner_read | fs::perms::group_read, fs::perms::owner_read | fs::perms::others_read,
                     fs::perms::owner_all | fs::perms::group_all | fs::perms::others_all,
                     fs::perms::owner_read | fs::perms::group_write}) {
    const fs::path p = write("open.key_secret", key + "\n", perms);
    const std::string why = refusal([&] { curve::read_secret_key_file(p); });
    EXPECT_NE(why.find("too open"), std::string::npos) << why;
    EXPECT_NE(why.find("chmod 600"), std::string::npos) << why;
    fs::remove(p);
  }
  EXPECT_EQ(curve::read_secret_key_file(write("ok.key_secret", "# comment\n\n" + key + "\n")), key);
  EXPECT_EQ(curve::read_secret_key_file(write("ro.key_secret", key, fs::perms::owner_read)), key);
  EXPECT_NE(refusal([&] { curve::read_secret_key_file(dir_ / "missing"); }).find("cannot read"), std::string::npos);
  // Owned by somebody else (only root can hand a file over; skipped otherwise).
  if (::geteuid() == 0) {
    const fs::path theirs = write("theirs.key_secret", key + "\n");
    ASSERT_EQ(::chown(theirs.c_str(), 4242, 4242), 0);
    EXPECT_NE(refusal([&] { curve::read_secret_key_file(theirs); }).find("owned by uid 4242"), std::string::npos);
  }
  EXPECT_NE(refusal([&] { curve::read_secret_key_file(dir_); }).find("regular file"), std::string::npos);
}

TEST_F(KeyDir, MalformedKeyFilesAreRefused) {
  const std::string a = curve::generate_key_pair().public_z85, b = curve::generate_key_pair().public_z85;
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"", "no key"},
      {"# only a comment\n", "no key"},
      {a.substr(0, 30) + "\n", "40 Z85 characters"},
      {a + "\n" + b + "\n", "more than one key"},
      {std::string(39, 'a') + "\"\n", "40 Z85 characters"},
      {std::string(5000, 'a'), "too big"},
  };
  for (const auto& [text, needle] : cases) {
    const fs::path p = write("bad.key", text);
    const std::string why = refusal([&] { curve::read_public_key_file(p); });
    EXPECT_NE(why.find(needle), std::string::npos) << "file \"" << text.substr(0, 60) << "\": " << why;
    EXPECT_NE(why.find(p.string()), std::string::npos) << why;
    fs::remove(p);
  }
  // A public and a secret key that are not one pair.
  curve::write_new_key_pair(prefix("one"));
  const curve::KeyPair other = curve::write_new_key_pair(prefix("two"));
  fs::remove(curve::public_key_path(prefix("one")));
  std::ofstream(curve::public_key_path(prefix("one"))) << other.public_z85 << '\n';
  EXPECT_NE(refusal([&] { curve::read_key_pair(prefix("one")); }).find("not one key pair"), std::string::npos);
}

// CURVE without a ZAP handler admits any client key; the server key must match.
TEST_F(KeyDir, KeysFromFilesCompleteARealHandshake) {
  const curve::KeyPair server = curve::write_new_key_pair(prefix("server"));
  curve::write_new_key_pair(prefix("client"));
  zmq::context_t ctx(1);
  zmq::socket_t router(ctx, zmq::socket_type::router);
  router.set(zmq::sockopt::linger, 0);
  curve::set_server_options(router, curve::read_secret_key_file(curve::secret_key_path(prefix("server"))), "test");
  router.bind("tcp://127.0.0.1:*");
  const std::string endpoint = router.get(zmq::sockopt::last_endpoint);

  auto client = [&](const std::string& server_public) {
    auto s = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::dealer);
    s->set(zmq::sockopt::linger, 0);
    curve::set_client_options(*s, {server_public, curve::read_key_pair(prefix("client"))});
    s->connect(endpoint);
    tp::send_request(*s, bp::make_status_request("hello"));
    return s;
  };
  auto good = client(curve::read_public_key_file(curve::public_key_path(prefix("server"))));
  const auto request = tp::receive_request(router, 5000ms);
  ASSERT_TRUE(request.has_value()) << "the handshake with the right keys failed";
  EXPECT_EQ(bp::decode(request->wire).request_id(), "hello");
  EXPECT_FALSE(request->user_id.has_value()) << "no ZAP handler: no User-Id";

  // A client that trusts another server key never gets through.
  auto wrong = client(curve::generate_key_pair().public_z85);
  EXPECT_FALSE(tp::receive_request(router, 1000ms).has_value());
  (void)server;
}

}  // namespace
