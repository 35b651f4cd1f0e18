#pragma once
// Wall-clock stage timing; every stage the user waits for is reported.
#include <chrono>

namespace brainshift {

class Stopwatch {
 public:
  Stopwatch() : start_(Clock::now()) {}
  double seconds() const {
    return std::chrono::duration<double>(Clock::now() - start_).count();
  }
  double lap() {
    const auto now = Clock::now();
    const double s = std::chrono::duration<double>(now - start_).count();
    start_ = now;
    return s;
  }

 private:
  using Clock = std::chrono::steady_clock;
  Clock::time_point start_;
};

}  // namespace brainshift
