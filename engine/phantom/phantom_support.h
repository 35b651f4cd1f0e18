#pragma once
// Small helpers shared by the phantom's deformation (phantom_deformation.cpp)
// and its images (brain_shift_phantom.cpp). Internal to engine/phantom.
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cstdint>
#include <thread>
#include <vector>

namespace brainshift::phantom_detail {

inline constexpr double kPi = 3.14159265358979323846;

inline Eigen::Matrix3d rotation_deg(const Eigen::Vector3d& deg) {
  const Eigen::Vector3d r = deg * kPi / 180.0;
  return (Eigen::AngleAxisd(r.z(), Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(r.y(), Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(r.x(), Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

inline std::array<bool, 65536> label_set(const std::vector<std::uint16_t>& labels) {
  std::array<bool, 65536> s{};
  for (auto l : labels) s[l] = true;
  return s;
}

// The q-quantile (0..1) of the values (0 when empty).
inline double quantile(std::vector<float> v, double q) {
  if (v.empty()) return 0;
  const auto at = v.begin() + static_cast<std::ptrdiff_t>(q * static_cast<double>(v.size() - 1));
  std::nth_element(v.begin(), at, v.end());
  return *at;
}

// Runs fn(k) for every slice k on two threads (the target machines have 2 cores).
template <class F>
void parallel_slices(int nk, F&& fn) {
  const int threads = std::max(1u, std::min(2u, std::thread::hardware_concurrency()));
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t)
    pool.emplace_back([&, t] {
      for (int k = t; k < nk; k += threads) fn(k);
    });
  for (auto& th : pool) th.join();
}

}  // namespace brainshift::phantom_detail
