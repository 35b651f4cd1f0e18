#pragma once
// The grid of head poses a registration sweeps when the head may be turned
// in its clamp (a lateral or temporal approach): yaw about the S-I axis every
// yaw_step_deg all round, pitch and roll 0 and +-tilt_deg. One home for the
// affine's sweep (registration/affine_registration.cpp) and the image-only
// placement's pose search (registration/intensity_placement.cpp), so both
// try the same poses in the same order (yaw outermost, then pitch, then
// roll). Why these steps: docs/DESIGN.md, "A head turned in its clamp".
#include <cmath>
#include <vector>

#include <Eigen/Geometry>

namespace brainshift {

struct SweptPose {
  double pitch_deg = 0, roll_deg = 0;  // about R-L (x) and A-P (y)
  double yaw_deg = 0;                  // about S-I (z), in [0, 360)
};

inline std::vector<SweptPose> swept_poses(double yaw_step_deg, double tilt_deg) {
  std::vector<SweptPose> poses;
  const int yaws = static_cast<int>(std::lround(360.0 / yaw_step_deg));
  for (int y = 0; y < yaws; ++y)
    for (const double pitch : {0.0, -tilt_deg, tilt_deg})
      for (const double roll : {0.0, -tilt_deg, tilt_deg}) poses.push_back({pitch, roll, y * yaw_step_deg});
  return poses;
}

// The pose's rotation: yaw after roll after pitch (z y x, as the placement's
// parameters compose).
inline Eigen::Matrix3d swept_pose_rotation(const SweptPose& pose) {
  const double deg = 3.14159265358979323846 / 180.0;
  return (Eigen::AngleAxisd(pose.yaw_deg * deg, Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(pose.roll_deg * deg, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(pose.pitch_deg * deg, Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

}  // namespace brainshift
