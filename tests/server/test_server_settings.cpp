#include <gtest/gtest.h>

#include <fstream>
#include <sstream>

#include "core/errors.h"
#include "server/server_settings.h"

using namespace brainshift;
using namespace brainshift::server;

TEST(ServerSettings, DefaultsWithoutSection) {
  const ServerSettings s = server_settings_from_text("[mesh]\ncell_size_mm = 3.0\n", "t.toml");
  EXPECT_EQ(s.endpoint, "tcp://127.0.0.1:5555");
  EXPECT_EQ(s.events, "tcp://127.0.0.1:5556");
  EXPECT_EQ(s.queue_depth, 4u);
  EXPECT_EQ(s.preop.kind, DefaultPreop::Kind::atlas);
  EXPECT_FALSE(s.allow_plain_tcp_non_loopback);
  EXPECT_EQ(s.timing_log_path(), std::filesystem::path("brainshift-store") / "timing.jsonl");
}

TEST(ServerSettings, ReadsEveryKey) {
  const ServerSettings s = server_settings_from_text(R"(
[server]
endpoint = "tcp://127.0.0.1:6000"
events = "ipc:///tmp/bs-events"
store = "/data/case7"
queue_depth = 9
max_frame_bytes = 4096
timing_log = "t.jsonl"
atlas_cache = "/cache"
preop = { t1 = "a.nii.gz", labels = "b.nii.gz", label_table = "c.json", patient_id = "MRN-0042 " }
allow_plain_tcp_non_loopback = true
)", "t.toml");
  EXPECT_EQ(s.endpoint, "tcp://127.0.0.1:6000");
  EXPECT_EQ(s.events, "ipc:///tmp/bs-events");
  EXPECT_EQ(s.store, "/data/case7");
  EXPECT_EQ(s.queue_depth, 9u);
  EXPECT_EQ(s.max_frame_bytes, 4096u);
  EXPECT_EQ(s.timing_log_path(), "/data/case7/t.jsonl");
  EXPECT_EQ(s.atlas_cache_path(), "/cache");
  EXPECT_EQ(s.preop.kind, DefaultPreop::Kind::files);
  EXPECT_EQ(s.preop.t1, "a.nii.gz");
  EXPECT_EQ(s.preop.labels, "b.nii.gz");
  EXPECT_EQ(s.preop.label_table, "c.json");
  EXPECT_EQ(s.preop.patient_id.value_or(""), "MRN-0042");  // DICOM's padding dropped
  EXPECT_TRUE(s.allow_plain_tcp_non_loopback);
}

TEST(ServerSettings, PreopNone) {
  EXPECT_EQ(server_settings_from_text("[server]\npreop = \"none\"\n", "t").preop.kind, DefaultPreop::Kind::none);
}

void expect_input_error(const std::string& text, const std::string& needle) {
  try {
    server_settings_from_text(text, "case.toml");
    FAIL() << "accepted: " << text;
  } catch (const InputError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("case.toml"), std::string::npos) << what;
    EXPECT_NE(what.find(needle), std::string::npos) << what;
  }
}

TEST(ServerSettings, RefusesBadValuesNamingTheKey) {
  expect_input_error("[server]\nendpont = \"x\"\n", "endpont");
  expect_input_error("[server]\nqueue_depth = 0\n", "queue_depth");
  expect_input_error("[server]\nqueue_depth = \"4\"\n", "queue_depth");
  expect_input_error("[server]\nmax_frame_bytes = 10\n", "max_frame_bytes");
  expect_input_error("[server]\npreop = \"atlass\"\n", "preop");
  expect_input_error("[server]\npreop = { t1 = \"a\" }\n", "preop");
  expect_input_error("[server]\npreop = { t1 = \"a\", labels = \"b\", extra = 1 }\n", "extra");
  expect_input_error("[server]\npreop = { t1 = \"a\", labels = \"b\", patient_id = \"  \" }\n", "patient_id");
  expect_input_error("[server]\nallow_plain_tcp_non_loopback = 1\n", "allow_plain_tcp_non_loopback");
  expect_input_error("[server\n", "parse error");
}

TEST(ServerSettings, PlainTcpOnlyOnLoopbackUnlessAllowed) {
  ServerSettings s;
  EXPECT_NO_THROW(validate_endpoints(s));
  s.endpoint = "tcp://10.0.0.5:5555";
  EXPECT_THROW(validate_endpoints(s), InputError);
  s.allow_plain_tcp_non_loopback = true;
  EXPECT_NO_THROW(validate_endpoints(s));
  s.endpoint = "udp://127.0.0.1:5";
  EXPECT_THROW(validate_endpoints(s), InputError);
  s = ServerSettings{};
  s.events = s.endpoint;
  EXPECT_THROW(validate_endpoints(s), InputError);
  EXPECT_TRUE(is_local_endpoint("tcp://localhost:1"));
  EXPECT_TRUE(is_local_endpoint("tcp://[::1]:1"));
  EXPECT_TRUE(is_local_endpoint("tcp://127.0.0.1:*"));
  EXPECT_FALSE(is_local_endpoint("tcp://0.0.0.0:5555"));
  EXPECT_FALSE(is_local_endpoint("tcp://*:5555"));
}

TEST(OpenIgtlinkSettings, OffOnLoopbackByDefault) {
  const ServerSettings s = server_settings_from_text("[server]\nqueue_depth = 2\n", "t.toml");
  EXPECT_FALSE(s.openigtlink.enabled);
  EXPECT_EQ(s.openigtlink.port, 18944);
  EXPECT_EQ(s.openigtlink.bind, "127.0.0.1");
  EXPECT_FALSE(s.openigtlink.allow_non_loopback);
  EXPECT_EQ(s.openigtlink.queue_messages, 32u);
  EXPECT_EQ(s.openigtlink.max_clients, 8u);
}

TEST(OpenIgtlinkSettings, ReadsEveryKey) {
  const ServerSettings s = server_settings_from_text(R"(
[openigtlink]
enabled = true
port = 0
bind = "10.1.2.3"
allow_non_loopback = true
queue_messages = 9
max_clients = 2
)", "t.toml");
  EXPECT_TRUE(s.openigtlink.enabled);
  EXPECT_EQ(s.openigtlink.port, 0);
  EXPECT_EQ(s.openigtlink.bind, "10.1.2.3");
  EXPECT_TRUE(s.openigtlink.allow_non_loopback);
  EXPECT_EQ(s.openigtlink.queue_messages, 9u);
  EXPECT_EQ(s.openigtlink.max_clients, 2u);
  EXPECT_NO_THROW(validate_endpoints(s));
}

TEST(OpenIgtlinkSettings, RefusesBadValuesNamingTheSectionAndKey) {
  expect_input_error("[openigtlink]\nenable = true\n", "[openigtlink] enable: unknown key");
  expect_input_error("[openigtlink]\nenabled = \"yes\"\n", "[openigtlink] enabled");
  expect_input_error("[openigtlink]\nport = 65536\n", "[openigtlink] port");
  expect_input_error("[openigtlink]\nport = -1\n", "[openigtlink] port");
  expect_input_error("[openigtlink]\nbind = 127\n", "[openigtlink] bind");
  expect_input_error("[openigtlink]\nqueue_messages = 7\n", "[openigtlink] queue_messages");
  expect_input_error("[openigtlink]\nmax_clients = 0\n", "[openigtlink] max_clients");
  expect_input_error("openigtlink = 1\n", "[openigtlink] must be a table");
}

TEST(OpenIgtlinkSettings, NonLoopbackBindOnlyWhenAllowed) {
  ServerSettings s;
  s.openigtlink.enabled = true;
  EXPECT_NO_THROW(validate_endpoints(s));
  s.openigtlink.bind = "127.4.5.6";
  EXPECT_NO_THROW(validate_endpoints(s));
  for (const char* bind : {"0.0.0.0", "192.168.1.20", "128.0.0.1"}) {
    s.openigtlink.bind = bind;
    try {
      validate_endpoints(s);
      FAIL() << "accepted bind " << bind;
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find("allow_non_loopback"), std::string::npos) << e.what();
    }
  }
  s.openigtlink.allow_non_loopback = true;
  EXPECT_NO_THROW(validate_endpoints(s));
  for (const char* bind : {"localhost", "::1", "127.0.0", ""}) {
    s.openigtlink.bind = bind;
    EXPECT_THROW(validate_endpoints(s), InputError) << bind;
  }
  s.openigtlink.enabled = false;  // not checked when off
  EXPECT_NO_THROW(validate_endpoints(s));
  EXPECT_TRUE(is_loopback_ipv4("127.0.0.1"));
  EXPECT_FALSE(is_loopback_ipv4("126.255.255.255"));
}

TEST(ServerSettings, ShippedConfigurationParses) {
  const ServerSettings s = server_settings_from_file(BRAINSHIFT_SOURCE_DIR "/config/brainshiftd.toml");
  EXPECT_NO_THROW(validate_endpoints(s));
  EXPECT_GE(s.queue_depth, 1u);
  // The shipped file states the defaults the code has.
  EXPECT_FALSE(s.openigtlink.enabled);
  EXPECT_EQ(s.openigtlink.port, OpenIgtlinkSettings{}.port);
  EXPECT_EQ(s.openigtlink.bind, OpenIgtlinkSettings{}.bind);
  EXPECT_EQ(s.openigtlink.queue_messages, OpenIgtlinkSettings{}.queue_messages);
}

TEST(ServerSettings, MissingFileIsAnInputError) {
  EXPECT_THROW(server_settings_from_file("/nonexistent/brainshiftd.toml"), InputError);
}
