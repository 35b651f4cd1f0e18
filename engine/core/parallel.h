#pragma once
// Two-way data parallelism for the intraop stages. The OR machines have two
// cores; at one MPI rank the second core is otherwise idle while the surgeon
// waits, and at two ranks the workers sleep between commands (see
// mpi_commands.cpp), so rank 0 may use both.
#include <algorithm>
#include <array>
#include <cstddef>
#include <exception>
#include <thread>

namespace brainshift {

// Work that already runs beside the stages on the second core (a check on its
// own thread) keeps its loops on that thread while this guard lives: split
// again, it would take time from the stages the surgeon waits for and finish
// no sooner than them. Results are the same either way (see below).
class SerialOnThisThread {
 public:
  SerialOnThisThread() : previous_(active()) { active() = true; }
  ~SerialOnThisThread() { active() = previous_; }
  SerialOnThisThread(const SerialOnThisThread&) = delete;
  SerialOnThisThread& operator=(const SerialOnThisThread&) = delete;
  static bool& active() {
    thread_local bool serial = false;
    return serial;
  }

 private:
  bool previous_;
};

// Runs fn(begin, end) on the two halves of [0, n), the upper half on a helper
// thread, when the machine has a second core and each half gets at least
// min_per_thread items; otherwise fn(0, n) on the calling thread. fn must only
// write state owned by its own range; with that, the result does not depend
// on the number of threads.
template <class Fn>
void parallel_halves(std::size_t n, std::size_t min_per_thread, Fn&& fn) {
  const bool two = !SerialOnThisThread::active() && std::thread::hardware_concurrency() >= 2 &&
                   n >= 2 * std::max<std::size_t>(1, min_per_thread);
  if (!two) {
    fn(std::size_t{0}, n);
    return;
  }
  const std::size_t mid = n / 2;
  std::exception_ptr helper_error;
  std::thread helper([&] {
    try {
      fn(mid, n);
    } catch (...) {
      helper_error = std::current_exception();
    }
  });
  try {
    fn(std::size_t{0}, mid);
  } catch (...) {
    helper.join();
    throw;
  }
  helper.join();
  if (helper_error) std::rethrow_exception(helper_error);
}

// fn(begin, end, half) on the two halves of [0, n) (half 0 or 1), side by side
// when there is a second core. Always the same two partial results, so sums
// reduced from them do not depend on the number of cores.
template <class Fn>
void on_two_halves(std::size_t n, Fn&& fn) {
  const std::size_t mid = n / 2;
  parallel_halves(2, 1, [&](std::size_t begin, std::size_t end) {
    for (std::size_t h = begin; h < end; ++h) fn(h == 0 ? 0 : mid, h == 0 ? mid : n, h);
  });
}

// f(v, i, j, k) for every voxel of a grid of dims (v its raster index), the
// slices in two halves side by side: for f that writes only its own voxel.
template <class F>
void for_each_voxel_on_both_cores(const std::array<int, 3>& dims, F&& f) {
  parallel_halves(static_cast<std::size_t>(dims[2]), 2, [&](std::size_t k0, std::size_t k1) {
    for (int k = static_cast<int>(k0); k < static_cast<int>(k1); ++k) {
      std::size_t v = static_cast<std::size_t>(k) * static_cast<std::size_t>(dims[0]) * static_cast<std::size_t>(dims[1]);
      for (int j = 0; j < dims[1]; ++j)
        for (int i = 0; i < dims[0]; ++i, ++v) f(v, i, j, k);
    }
  });
}

}  // namespace brainshift
