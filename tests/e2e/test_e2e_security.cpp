// CURVE end to end with the real binaries: `brainshift keygen` makes the keys,
// brainshiftd serves only the listed ones, clients with the right keys are
// served (requests and `watch`), clients without or with unknown keys get a
// timeout that names authentication, and unsafe configurations are refused
// at start-up. No preop is loaded: nothing here needs the engine warm.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <thread>

#include <nlohmann/json.hpp>

#include "client/exit_codes.h"
#include "process.h"
#include "temp_dir.h"

using namespace brainshift::e2e;
namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace cli = brainshift::cli;

namespace {

class SecurityE2E : public ::testing::Test {
 protected:
  void TearDown() override {
    if (HasFailure()) tmp_.keep();
  }
  fs::path path(const std::string& name) const { return dir_ / name; }

  // The public key `keygen` printed.
  std::string keygen(const std::string& name) const {
    const RunResult r = run({BRAINSHIFT_BIN, "keygen", "--out", path(name).string()}, dir_, 30);
    EXPECT_EQ(r.code, 0) << r.err;
    return r.out.substr(0, r.out.find('\n'));
  }
  void write_config(const std::string& body) const { std::ofstream(path("d.toml")) << body; }

  // brainshiftd on ports the OS picks; waits for its ready file.
  std::unique_ptr<Process> start_daemon(std::string& endpoint, std::string& events) const {
    auto p = std::make_unique<Process>(
        std::vector<std::string>{BRAINSHIFTD_BIN, "--config", path("d.toml").string(), "--store",
                                 path("store").string(), "--endpoint", "tcp://127.0.0.1:*", "--events",
                                 "tcp://127.0.0.1:*", "--ready-file", path("ready.json").string()},
        path("daemon.out"), path("daemon.err"));
    for (int i = 0; i < 1200 && !fs::exists(path("ready.json")) && p->running(); ++i) std::this_thread::sleep_for(50ms);
    if (!fs::exists(path("ready.json"))) throw std::runtime_error("brainshiftd did not start: " + read_file(path("daemon.err")));
    const auto ready = nlohmann::json::parse(read_file(path("ready.json")));
    endpoint = ready.at("endpoint").get<std::string>();
    events = ready.at("events").get<std::string>();
    return p;
  }
  // A client command as `who` (a key prefix, or "" for no CURVE).
  RunResult client(const std::string& endpoint, const std::string& who, std::vector<std::string> args,
                   const std::string& timeout = "10") const {
    std::vector<std::string> argv = {BRAINSHIFT_BIN, "--server", endpoint, "--timeout", timeout};
    if (!who.empty()) argv.insert(argv.end(), {"--key", path(who).string(), "--server-key", path("server.key").string()});
    argv.insert(argv.end(), args.begin(), args.end());
    return run(argv, dir_, 60);
  }

  brainshift::test::TempDir tmp_{"e2e-security"};
  const fs::path& dir_ = tmp_.path();
};

TEST_F(SecurityE2E, KeygenKeysWorkThroughARealCurveHandshake) {
  const std::string server_key = keygen("server");
  const std::string admin = keygen("admin"), viewer = keygen("viewer");
  keygen("stranger");
  ASSERT_EQ(server_key.size(), 40u);
  struct stat st {};
  ASSERT_EQ(::stat(path("admin.key_secret").c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  EXPECT_NE(read_file(path("admin.key")).find(admin), std::string::npos);
  const RunResult again = run({BRAINSHIFT_BIN, "keygen", "--out", path("admin").string()}, dir_, 30);
  EXPECT_EQ(again.code, cli::kExitUsage);
  EXPECT_NE(again.err.find("never overwritten"), std::string::npos) << again.err;

  // Relative key paths are read beside the configuration file; the viewer
  // comes from an allow-list file, the admin from the configuration itself.
  std::ofstream(path("clients.toml")) << "[[clients]]\nname = \"wall\"\nrole = \"viewer\"\npublic_key = \"" << viewer
                                      << "\"\n";
  write_config("[server]\npreop = \"none\"\n\n[security]\ncurve = true\nserver_secret_key_file = \"server.key_secret\"\n"
               "server_public_key_file = \"server.key\"\nclients_file = \"clients.toml\"\n\n[[security.clients]]\n"
               "name = \"it\"\nrole = \"admin\"\npublic_key = \"" + admin + "\"\n");
  std::string endpoint, events;
  auto daemon = start_daemon(endpoint, events);

  const RunResult status = client(endpoint, "admin", {"status"});
  EXPECT_EQ(status.code, 0) << status.err;
  EXPECT_NE(status.out.find("state:   idle"), std::string::npos) << status.out;
  EXPECT_EQ(client(endpoint, "viewer", {"list"}).code, 0);

  // No key, or a key the server does not list: a timeout whose message names authentication.
  const RunResult plain = client(endpoint, "", {"status"}, "1");
  EXPECT_EQ(plain.code, cli::kExitUnreachable);
  EXPECT_NE(plain.err.find("--key and --server-key"), std::string::npos) << plain.err;
  const RunResult stranger = client(endpoint, "stranger", {"status"}, "1");
  EXPECT_EQ(stranger.code, cli::kExitUnreachable);
  EXPECT_NE(stranger.err.find("allow-list"), std::string::npos) << stranger.err;
  // watch is refused the same way and says so instead of waiting silently.
  for (const std::string who : {"stranger", ""}) {
    std::vector<std::string> argv = {BRAINSHIFT_BIN, "--events", events};
    if (!who.empty()) argv.insert(argv.end(), {"--key", path(who).string(), "--server-key", path("server.key").string()});
    argv.insert(argv.end(), {"watch", "--for", "30"});
    const RunResult w = run(argv, dir_, 60);
    EXPECT_EQ(w.code, cli::kExitUnreachable) << who << ": " << w.err;
    EXPECT_NE(w.err.find(who.empty() ? "--key and --server-key" : "allow-list"), std::string::npos) << w.err;
  }
  // A role that may not: a typed server error.
  const RunResult viewer_stop = client(endpoint, "viewer", {"shutdown"});
  EXPECT_EQ(viewer_stop.code, cli::kExitError);
  EXPECT_NE(viewer_stop.err.find("unauthorised"), std::string::npos) << viewer_stop.err;

  // watch over CURVE: the viewer sees the shutdown event.
  Process watcher({BRAINSHIFT_BIN, "--events", events, "--key", path("viewer").string(), "--server-key",
                   path("server.key").string(), "watch", "--json", "--count", "1", "--for", "60"},
                  path("watch.out"), path("watch.err"));
  std::this_thread::sleep_for(1000ms);  // PUB/SUB: the subscription must be in place first
  EXPECT_EQ(client(endpoint, "admin", {"shutdown", "--reason", "e2e"}).code, 0);
  EXPECT_EQ(daemon->wait(60).value_or(-1), 0);
  EXPECT_EQ(watcher.wait(60).value_or(-1), 0);
  EXPECT_NE(read_file(path("watch.out")).find("event.server.shutdown"), std::string::npos)
      << read_file(path("watch.err"));

  // The log names the refused key by its fingerprint and never holds a secret.
  const std::string log = read_file(path("daemon.out")) + read_file(path("daemon.err"));  // spdlog: stdout
  EXPECT_NE(log.find("key not in the allow-list"), std::string::npos) << log;
  for (const char* who : {"server", "admin", "viewer", "stranger"}) {
    const std::string secret = read_file(path(std::string(who) + ".key_secret"));
    const std::string key = secret.substr(secret.rfind('\n', secret.size() - 2) + 1, 40);
    EXPECT_EQ(log.find(key), std::string::npos) << who << "'s secret key is in the log";
  }
}

TEST_F(SecurityE2E, UnsafeConfigurationsAreRefusedAtStartUp) {
  write_config("[server]\npreop = \"none\"\n");
  const RunResult open = run({BRAINSHIFTD_BIN, "--config", path("d.toml").string(), "--store", path("store").string(),
                              "--endpoint", "tcp://0.0.0.0:0"},
                             dir_, 60);
  EXPECT_EQ(open.code, 2);
  EXPECT_NE(open.out.find("tcp://0.0.0.0:0"), std::string::npos) << open.out;
  EXPECT_NE(open.out.find("requires CURVE"), std::string::npos) << open.out;

  const std::string key = keygen("server");
  fs::permissions(path("server.key_secret"), fs::perms::others_read, fs::perm_options::add);
  write_config("[server]\npreop = \"none\"\n[security]\ncurve = true\nserver_secret_key_file = \"server.key_secret\"\n"
               "[[security.clients]]\nname = \"x\"\nrole = \"viewer\"\npublic_key = \"" + key + "\"\n");
  const RunResult readable = run({BRAINSHIFTD_BIN, "--config", path("d.toml").string(), "--store",
                                  path("store").string(), "--endpoint", "tcp://127.0.0.1:*", "--events",
                                  "tcp://127.0.0.1:*"},
                                 dir_, 120);
  EXPECT_NE(readable.code, 0);
  EXPECT_NE(readable.out.find("too open"), std::string::npos) << readable.out;

  // The client checks its own keys the same way, before any connection.
  keygen("client");
  const RunResult half = run({BRAINSHIFT_BIN, "--key", path("client").string(), "status"}, dir_, 30);
  EXPECT_EQ(half.code, cli::kExitUsage);
  EXPECT_NE(half.err.find("both --key"), std::string::npos) << half.err;
  fs::permissions(path("client.key_secret"), fs::perms::group_read, fs::perm_options::add);
  const RunResult open_key = run({BRAINSHIFT_BIN, "--key", path("client").string(), "--server-key",
                                  path("server.key").string(), "status"},
                                 dir_, 30);
  EXPECT_EQ(open_key.code, 2);
  EXPECT_NE(open_key.err.find("too open"), std::string::npos) << open_key.err;
}

}  // namespace
