// A 3D Slicer stand-in for the daemon latency benchmark (IGTL=1
// daemon_latency_bench.sh): receives OpenIGTLink results with the library's
// client classes and reports, per result, the time from the result's
// time stamp (when the daemon stored it, just before event.scan.done) to the
// arrival of its last message. Prints JSON.
#include <algorithm>
#include <chrono>
#include <iostream>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "igtl_receiver.h"

int main(int argc, char** argv) {
  CLI::App app{"receives OpenIGTLink results and times them"};
  int port = 18944, results = 1;
  double timeout_s = 600;
  app.add_option("--port", port, "OpenIGTLink port on 127.0.0.1")->required();
  app.add_option("--results", results, "results to receive (the one queued on connect is skipped if stale)");
  app.add_option("--timeout", timeout_s, "seconds to wait for each result");
  CLI11_PARSE(app, argc, argv);
  brainshift::test::IgtlReceiver receiver(port, std::chrono::milliseconds(static_cast<long>(timeout_s * 1000)));
  std::vector<double> latency_s;
  std::size_t bytes = 0;
  for (int i = 0; i < results; ++i) {
    const auto result = receiver.next_result();
    const auto now = std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
    const auto& status = result.back();
    latency_s.push_back(now - (status.seconds + status.fraction / 4294967296.0));
    for (const auto& m : result) bytes += static_cast<std::size_t>(m.message->GetPackSize());
  }
  std::vector<double> sorted = latency_s;
  std::sort(sorted.begin(), sorted.end());
  std::cout << nlohmann::json{{"results", results},
                              {"megabytes_per_result", bytes / 1e6 / std::max(1, results)},
                              {"stored_to_received_s", {{"p50", sorted[sorted.size() / 2]}, {"max", sorted.back()}}},
                              {"each_s", latency_s}}
                   .dump()
            << '\n';
  return 0;
}
