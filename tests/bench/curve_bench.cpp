// What CURVE costs on the wire: round trips of one large frame
// DEALER -> ROUTER -> DEALER over tcp loopback, plain and with CURVE (the
// daemon's socket options, protocol/curve_keys.h). Prints one JSON line per
// mode; run by hand, never a timed test.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <zmq.hpp>

#include "protocol/curve_keys.h"

namespace curve = brainshift::protocol::curve;

namespace {

std::vector<double> round_trips_s(bool use_curve, std::size_t frame_bytes, int repeats) {
  zmq::context_t ctx(1);
  zmq::socket_t router(ctx, zmq::socket_type::router), dealer(ctx, zmq::socket_type::dealer);
  if (use_curve) {
    const curve::KeyPair server = curve::generate_key_pair(), client = curve::generate_key_pair();
    curve::set_server_options(router, server.secret_z85, "bench");
    curve::set_client_options(dealer, {server.public_z85, client});
  }
  router.bind("tcp://127.0.0.1:*");
  dealer.connect(router.get(zmq::sockopt::last_endpoint));
  const std::string payload(frame_bytes, 'x');
  std::vector<double> seconds;
  for (int i = 0; i < repeats; ++i) {
    const auto t0 = std::chrono::steady_clock::now();
    dealer.send(zmq::buffer(payload));
    zmq::message_t id, body, back;
    (void)router.recv(id);
    (void)router.recv(body);
    router.send(id, zmq::send_flags::sndmore);
    router.send(body, zmq::send_flags::none);
    (void)dealer.recv(back);
    seconds.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  }
  std::sort(seconds.begin(), seconds.end());
  return seconds;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"round trip of one frame, plain TCP vs CURVE"};
  std::size_t megabytes = 50;
  int repeats = 7;
  app.add_option("--mb", megabytes, "frame size in MiB");
  app.add_option("--repeats", repeats, "round trips per mode")->check(CLI::PositiveNumber);
  CLI11_PARSE(app, argc, argv);
  for (const bool use_curve : {false, true}) {
    const auto s = round_trips_s(use_curve, megabytes << 20, repeats);
    std::printf("%s\n", nlohmann::json{{"bench", "curve_round_trip"},
                                       {"curve", use_curve},
                                       {"frame_mib", megabytes},
                                       {"repeats", repeats},
                                       {"median_s", s[s.size() / 2]},
                                       {"min_s", s.front()},
                                       {"max_s", s.back()}}
                                .dump()
                                .c_str());
  }
}
