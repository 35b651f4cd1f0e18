// [security] configuration, its start-up checks, the server's key files and
// allow-list, and the role table (PROTOCOL.md section 13) applied by ServerCore.
#include <gtest/gtest.h>

#include <fstream>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "protocol/media.h"
#include "protocol/curve_keys.h"
#include "protocol/requests.h"
#include "server/case_store.h"
#include "server/curve_auth.h"
#include "server/server_core.h"
#include "server/server_settings.h"
#include "test_support.h"

using namespace brainshift;
using namespace brainshift::server;
using namespace brainshift::protocol;
namespace curve = brainshift::protocol::curve;
namespace fs = std::filesystem;

namespace {

// The InputError message of fn ("" when it throws none).
template <class Fn>
std::string input_error(Fn&& fn) {
  try {
    fn();
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}

std::string client_entry(const std::string& name, const std::string& role, const std::string& key) {
  return "[[security.clients]]\nname = \"" + name + "\"\nrole = \"" + role + "\"\npublic_key = \"" + key + "\"\n";
}

TEST(SecuritySettings, DefaultsAreOffAndShutdownNeedsAuthentication) {
  const ServerSettings s = server_settings_from_text("[server]\n", "t.toml");
  EXPECT_FALSE(s.security.curve);
  EXPECT_FALSE(s.security.allow_unauthenticated_shutdown);
  EXPECT_TRUE(s.security.clients.empty());
  EXPECT_NO_THROW(validate_endpoints(s));
}

TEST(SecuritySettings, ReadsEveryKeyAndResolvesPathsBesideTheConfig) {
  const std::string key = curve::generate_key_pair().public_z85;
  const ServerSettings s = server_settings_from_text(R"([security]
curve = true
server_secret_key_file = "keys/server.key_secret"
server_public_key_file = "/etc/brainshift/server.key"
clients_file = "clients.toml"
allow_unauthenticated_shutdown = true
)" + client_entry("or1", "scanner", key) + client_entry("viewer", "viewer", curve::generate_key_pair().public_z85),
                                                     "t.toml", "/etc/brainshift");
  EXPECT_TRUE(s.security.curve);
  EXPECT_EQ(s.security.server_secret_key_file, "/etc/brainshift/keys/server.key_secret");
  EXPECT_EQ(s.security.server_public_key_file, "/etc/brainshift/server.key");
  EXPECT_EQ(s.security.clients_file, "/etc/brainshift/clients.toml");
  EXPECT_TRUE(s.security.allow_unauthenticated_shutdown);
  ASSERT_EQ(s.security.clients.size(), 2u);
  EXPECT_EQ(s.security.clients[0].name, "or1");
  EXPECT_EQ(s.security.clients[0].role, Role::scanner);
  EXPECT_EQ(s.security.clients[0].public_z85, key);
  EXPECT_EQ(s.security.clients[1].role, Role::viewer);
}

TEST(SecuritySettings, BadEntriesAreNamed) {
  const std::string key = curve::generate_key_pair().public_z85;
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"[security]\ncurve = \"yes\"\n", "curve: must be true or false"},
      {"[security]\nkey = \"inline secrets are not read\"\n", "key: unknown key"},
      {"[security]\nserver_secret_key_file = 3\n", "server_secret_key_file: must be a string"},
      {client_entry("or1", "root", key), "role: must be"},
      {client_entry("or1", "scanner", key.substr(1)), "public_key: not a CURVE public key"},
      {client_entry("", "scanner", key), "name: 1..64"},
      {"[[security.clients]]\nname = \"x\"\nrole = \"admin\"\n", "public_key: required"},
      {client_entry("or1", "scanner", key) + "secret_key = \"x\"\n", "secret_key: unknown key"},
      {"[security]\nclients = 5\n", "must be an array of tables"},
  };
  for (const auto& [text, needle] : cases) {
    const std::string why = input_error([&] { server_settings_from_text(text, "case.toml"); });
    EXPECT_NE(why.find("case.toml"), std::string::npos) << text << " -> " << why;
    EXPECT_NE(why.find(needle), std::string::npos) << text << " -> " << why;
  }
}

TEST(SecuritySettings, NonLoopbackNeedsCurveOrAnExplicitPlainTcpChoice) {
  ServerSettings s;
  s.endpoint = "tcp://0.0.0.0:5555";
  const std::string why = input_error([&] { validate_endpoints(s); });
  EXPECT_NE(why.find("tcp://0.0.0.0:5555"), std::string::npos) << why;
  EXPECT_NE(why.find("requires CURVE"), std::string::npos) << why;
  s.endpoint = "tcp://127.0.0.1:5555";
  s.events = "tcp://192.168.1.20:5556";
  EXPECT_NE(input_error([&] { validate_endpoints(s); }).find("server.events \"tcp://192.168.1.20:5556\""),
            std::string::npos);
  s.allow_plain_tcp_non_loopback = true;
  EXPECT_NO_THROW(validate_endpoints(s));

  // CURVE makes any endpoint acceptable, but needs its key and an allow-list.
  s.allow_plain_tcp_non_loopback = false;
  s.security.curve = true;
  EXPECT_NE(input_error([&] { validate_endpoints(s); }).find("server_secret_key_file"), std::string::npos);
  s.security.server_secret_key_file = "server.key_secret";
  EXPECT_NE(input_error([&] { validate_endpoints(s); }).find("allow-list"), std::string::npos);
  s.security.clients_file = "clients.toml";
  EXPECT_NO_THROW(validate_endpoints(s));
  s.endpoint = "inproc://x";
  EXPECT_NE(input_error([&] { validate_endpoints(s); }).find("CURVE needs a tcp://"), std::string::npos);
}

class ServerKeys : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = curve::write_new_key_pair(prefix("server"));
    s_.curve = true;
    s_.server_secret_key_file = curve::secret_key_path(prefix("server"));
    s_.server_public_key_file = curve::public_key_path(prefix("server"));
    s_.clients = {{"or1", Role::scanner, curve::generate_key_pair().public_z85}};
  }
  std::string prefix(const std::string& name) const { return (dir_.path() / name).string(); }
  fs::path write(const std::string& name, const std::string& text) const {
    std::ofstream(dir_.path() / name) << text;
    return dir_.path() / name;
  }
  test::TempDir dir_;
  curve::KeyPair server_;
  SecuritySettings s_;
};

TEST_F(ServerKeys, LoadsKeysAndMergesTheAllowListFile) {
  const std::string viewer = curve::generate_key_pair().public_z85;
  s_.clients_file = write("clients.toml", "[[clients]]\nname = \"wall\"\nrole = \"viewer\"\npublic_key = \"" + viewer + "\"\n");
  const ServerCurve c = load_server_curve(s_);
  EXPECT_EQ(c.server.public_z85, server_.public_z85);
  EXPECT_EQ(c.server.secret_z85, server_.secret_z85);
  ASSERT_EQ(c.clients_by_key.size(), 2u);
  EXPECT_EQ(c.clients_by_key.at(curve::z85_to_binary(viewer)).role, Role::viewer);
  EXPECT_EQ(c.clients_by_key.at(curve::z85_to_binary(s_.clients[0].public_z85)).name, "or1");
}

TEST_F(ServerKeys, WorldReadableSecretKeyIsRefused) {
  fs::permissions(s_.server_secret_key_file, fs::perms::others_read, fs::perm_options::add);
  const std::string why = input_error([&] { load_server_curve(s_); });
  EXPECT_NE(why.find("too open"), std::string::npos) << why;
  EXPECT_NE(why.find(s_.server_secret_key_file.string()), std::string::npos) << why;
  fs::permissions(s_.server_secret_key_file, fs::perms::owner_read | fs::perms::owner_write | fs::perms::group_read);
  EXPECT_NE(input_error([&] { load_server_curve(s_); }).find("too open"), std::string::npos);
}

TEST_F(ServerKeys, MalformedOrMismatchedKeysAreRefused) {
  // The secret key file holds something else.
  const fs::path garbage = write("garbage.key_secret", "not a key\n");
  fs::permissions(garbage, fs::perms::owner_read | fs::perms::owner_write);
  SecuritySettings bad = s_;
  bad.server_secret_key_file = garbage;
  EXPECT_NE(input_error([&] { load_server_curve(bad); }).find("40 Z85 characters"), std::string::npos);
  bad.server_secret_key_file = dir_.path() / "missing.key_secret";
  EXPECT_NE(input_error([&] { load_server_curve(bad); }).find("cannot read"), std::string::npos);
  // The public key file belongs to another pair.
  bad = s_;
  bad.server_public_key_file = write("other.key", curve::generate_key_pair().public_z85 + "\n");
  EXPECT_NE(input_error([&] { load_server_curve(bad); }).find("is not the public key of"), std::string::npos);
  // The same client key twice, or the same name twice.
  bad = s_;
  bad.clients.push_back({"other", Role::admin, s_.clients[0].public_z85});
  EXPECT_NE(input_error([&] { load_server_curve(bad); }).find("listed twice"), std::string::npos);
  bad = s_;
  bad.clients.push_back({"or1", Role::admin, curve::generate_key_pair().public_z85});
  EXPECT_NE(input_error([&] { load_server_curve(bad); }).find("\"or1\" is listed twice"), std::string::npos);
  // An allow-list file with anything but [[clients]].
  bad = s_;
  bad.clients_file = write("bad-clients.toml", "[server]\nendpoint = \"x\"\n");
  EXPECT_NE(input_error([&] { load_server_curve(bad); }).find("only [[clients]]"), std::string::npos);
  bad.clients_file = write("broken.toml", "[[clients]\n");
  EXPECT_NE(input_error([&] { load_server_curve(bad); }).find("TOML parse error"), std::string::npos);
}

TEST(Roles, TableOfProtocolSection13) {
  const Peer scanner = Peer::from_zap("scanner", "s"), viewer = Peer::from_zap("viewer", "v"),
             admin = Peer::from_zap("admin", "a"), unknown_role = Peer::from_zap("root", "r"),
             no_role = Peer::from_zap(std::nullopt, std::nullopt), local = Peer::unauthenticated_local();
  using T = MessageType;
  struct Row {
    T type;
    bool scanner, viewer, admin;
  };
  for (const Row& r : {Row{T::kStatus, true, true, true}, Row{T::kScanList, true, true, true}, Row{T::kLabelsGet, true, true, true},
                       Row{T::kScanResult, true, true, true}, Row{T::kScanPush, true, false, true},
                       Row{T::kPreopLoad, false, false, true}, Row{T::kShutdown, false, false, true}}) {
    const std::string name(to_string(r.type));
    EXPECT_EQ(!refusal(scanner, r.type, false), r.scanner) << name;
    EXPECT_EQ(!refusal(viewer, r.type, false), r.viewer) << name;
    EXPECT_EQ(!refusal(admin, r.type, false), r.admin) << name;
    EXPECT_TRUE(refusal(unknown_role, r.type, true)) << name;
    EXPECT_TRUE(refusal(no_role, r.type, true)) << name;
    // Without CURVE: admin, except shutdown unless allowed.
    EXPECT_EQ(!refusal(local, r.type, false), r.type != T::kShutdown) << name;
    EXPECT_FALSE(refusal(local, r.type, true)) << name;
  }
  EXPECT_NE(refusal(viewer, T::kScanPush, false)->find("viewer"), std::string::npos);
}

TEST(Roles, ServerCoreRefusesBeforeReadingTheRequest) {
  test::IdleServer server;
  ServerCore& core = *server.core;
  const Peer viewer = Peer::from_zap("viewer", "wall");
  // A scan.push without its labels frame: invalid for a scanner, unauthorised for a viewer.
  const Message bare_push = make_message(MessageType::kScanPush, "v1");
  auto code = [](const Message& reply) { return parse_error_reply(reply).code; };
  EXPECT_EQ(code(core.handle_wire(encode(bare_push), viewer)), ErrorCode::kUnauthorised);
  EXPECT_EQ(core.handle_wire(encode(bare_push), viewer).request_id(), "v1");
  EXPECT_EQ(code(core.handle_wire(encode(bare_push), Peer::from_zap("scanner", "s"))), ErrorCode::kInvalidRequest);
  // Without CURVE a shutdown is refused unless configured, and nothing stops.
  EXPECT_EQ(code(core.handle_wire(encode(make_shutdown_request("x")))), ErrorCode::kUnauthorised);
  EXPECT_FALSE(core.shutdown_requested());
  EXPECT_EQ(core.handle_wire(encode(make_status_request("s"))).type(), MessageType::kStatusReply);
  EXPECT_EQ(core.handle_wire(encode(make_shutdown_request("x")), Peer::from_zap("admin", "a")).type(),
            MessageType::kShutdownReply);
  EXPECT_TRUE(core.shutdown_requested());
}

}  // namespace

namespace {

// No request field is ever a path the server opens: paths in a header are
// ignored, ids are only looked up in the store's index, and store paths are
// made of server-assigned ids.
TEST(ClientPaths, AreNeverOpened) {
  test::IdleServer server;
  ServerCore& core = *server.core;
  auto code = [](const Message& reply) {
    return reply.type() == MessageType::kError ? parse_error_reply(reply).code : ErrorCode::kInternal;
  };
  // A preop.load naming files instead of sending frames is refused; nothing loads.
  Message named = make_message(MessageType::kPreopLoad, "p");
  named.header["t1"] = (server.settings.store / "preop.h5").string();
  named.header["labels"] = "/etc/passwd";
  named.header["path"] = "/etc/shadow";
  EXPECT_EQ(code(core.handle_wire(encode(named))), ErrorCode::kInvalidRequest);
  EXPECT_FALSE(core.step(std::chrono::milliseconds(1)));
  EXPECT_EQ(core.status().state, ServerState::kIdle);

  // Load the double's atlas, push with a path-like client id, then ask for path-like scan ids.
  PreopLoadRequest atlas;
  atlas.use_default_atlas = true;
  ASSERT_EQ(core.handle_wire(encode(make_preop_load_request("a", atlas))).type(), MessageType::kPreopLoadReply);
  ASSERT_TRUE(core.step(std::chrono::milliseconds(10)));
  ScanPushRequest push;
  push.labels = media::nifti_frame("labels", label_image_to_bytes(test::ball_labels(12), true));
  push.client_scan_id = "../../escape";
  const Message pushed = core.handle_wire(encode(make_scan_push_request("s", push)));
  ASSERT_EQ(pushed.type(), MessageType::kScanPushReply) << pushed.header.dump();
  ASSERT_TRUE(core.step(std::chrono::milliseconds(10)));
  for (const auto& e : fs::directory_iterator(server.settings.store / "scans"))
    EXPECT_EQ(e.path().filename().string().rfind("scan-", 0), 0u) << e.path();
  EXPECT_FALSE(fs::exists(server.dir.path() / "escape"));
  for (const char* id : {"../preop.h5", "../../store/scans/scan-000001", "scans/scan-000001", "/etc/passwd"}) {
    const Message r = core.handle_wire(encode(make_scan_result_request("r", {id, {ResultPart::kDisplacement}, {}})));
    EXPECT_EQ(code(r), ErrorCode::kNotFound) << id;
  }
  EXPECT_EQ(core.handle_wire(encode(make_scan_result_request("r", {parse_scan_push_reply(pushed).scan_id,
                                                                    {ResultPart::kDisplacement}, {}})))
                .type(),
            MessageType::kScanResultReply);
}

}  // namespace
