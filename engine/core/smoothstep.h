#pragma once
// The cubic ramp 3t^2 - 2t^3, 0 for t <= 0 and 1 for t >= 1: fades and tapers
// without a kink at either end.
#include <algorithm>

namespace brainshift {

inline double smoothstep(double t) {
  t = std::clamp(t, 0.0, 1.0);
  return t * t * (3.0 - 2.0 * t);
}

}  // namespace brainshift
